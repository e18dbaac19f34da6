"""``exact`` traces the reference lattices with the march that traces generated wood, and matches
the independent exact tracer (ray-circle and ray-line roots, :meth:`Lattice.trace`) ray by ray."""

import numpy as np
import pytest

from pipeline.optics.lattice import honeycomb, tube_lattice
from pipeline.optics.rays import square_beam
from pipeline.optics.settings import Optics, settings_for
from pipeline.optics.trace import trace

LATTICES = {
    "tubes-square": tube_lattice(14.5, 7.25, 2.0, jitter=0.15, seed=3),  # merged and separate tubes
    "tubes-hex": tube_lattice(14.5, 7.25, 2.0, packing="hex", seed=3),  # every tube touches six others
    "cells-hex": honeycomb(14.5, 2.0, jitter=0.15, seed=3),
    "cells-square": honeycomb(14.5, 2.0, packing="square", seed=2),
}
NUDGE_UM = 1e-12  # moving a ray's entry point this far shows whether rounding can part it


def _angle(u, v):
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.einsum("ij,ij->i", u, v))


def _three(lat, thickness, n_wall, rays=300):
    """The march (``exact``), the independent tracer, and the independent tracer with its entry
    points nudged by NUDGE_UM: what rounding alone does to a ray."""
    beam = square_beam(rays, 150.0, seed=1, direction=(0.2, 1.0, 0.1))
    d = beam.unit_directions()
    march = trace(lat.slab(thickness), beam, Optics(n_wall, 1.49), settings_for("exact"))
    ref = lat.trace_independently(beam.origins, d, n_wall=n_wall, n_poly=1.49, thickness_um=thickness)
    nudged = lat.trace_independently(beam.origins + [NUDGE_UM, 0.0, 0.0], d, n_wall=n_wall, n_poly=1.49, thickness_um=thickness)
    return beam, march, ref, nudged


@pytest.mark.parametrize("n_wall", [1.53, 1.45])
@pytest.mark.parametrize("name", list(LATTICES))
def test_thin_lattices_match_the_independent_tracer_ray_by_ray(name, n_wall):
    """30 µm, both signs of ΔRI, 3-D directions: every ray meets the same interfaces and ends with
    the same status; every exit direction agrees to 1e-9 rad, except rays that a 1e-12 µm nudge
    of the entry point parts as well (a chain of grazing reflections amplifying rounding)."""
    lat = LATTICES[name]
    _, march, ref, nudged = _three(lat, 30.0, n_wall)
    assert np.array_equal(march.events, ref.events) and np.array_equal(march.status, ref.status)
    assert march.events.mean() > 3
    sensitive = _angle(ref.direction, nudged.direction) > 1e-10
    assert sensitive.mean() <= 0.01
    ang = _angle(march.direction, ref.direction)
    assert ang[~sensitive].max() <= 1e-9, (name, ang.max())
    # The reference steps 1e-9 µm past each honeycomb crossing: paths agree to that per interface.
    np.testing.assert_allclose(march.path[~sensitive], ref.path[~sensitive], rtol=0, atol=1e-8 + 2e-9 * ref.events.max())


@pytest.mark.parametrize("name", ["tubes-square", "tubes-hex", "cells-hex"])
def test_on_thick_lattices_the_rays_that_part_are_parted_by_rounding_or_a_sliver(name):
    """300 µm (50–90 interfaces a ray): the few rays that part from the reference are rays that the
    1e-12 µm nudge parts too, or rays that cross a polymer sliver thinner than 1e-7 µm where two
    tubes touch (the reference samples the phase 1e-8 µm past a crossing and steps over it); the
    distributions agree."""
    lat = LATTICES[name]
    beam, march, ref, nudged = _three(lat, 300.0, 1.53)
    assert march.events.mean() > 40
    ang = _angle(march.direction, ref.direction)
    rounding = _angle(ref.direction, nudged.direction) > 1e-10
    parted = np.flatnonzero((ang > 1e-9) & ~rounding)
    if parted.size:
        log = lat.slab(300.0).march_walls(beam.origins[parted], beam.unit_directions()[parted], n_wall=1.53,
                                             n_poly=1.49, max_events=10_000, log_events=400)["log"]
        gaps = np.linalg.norm(np.diff(log[:, :, :3], axis=1), axis=2)
        sliver = ((gaps < 1e-7) & (log[:, 1:, 11] != log[:, :-1, 11])).any(axis=1)
        assert sliver.all(), parted[~sliver]
    assert (ang > 1e-6).mean() <= 2 * (_angle(ref.direction, nudged.direction) > 1e-6).mean() + 0.01
    te, tr = march.transmitted, ref.transmitted
    assert abs(te.mean() - tr.mean()) <= 0.01
    from scipy import stats

    assert stats.ks_2samp(march.theta_r[te], ref.theta_r[tr]).statistic <= 0.05


def test_fresnel_on_a_lattice_reflects_some_rays_and_is_reproducible():
    """Through the march a lattice has Fresnel reflection as generated wood does: drawn per ray and
    interface, so the same seed gives the same rays."""
    lat = LATTICES["cells-hex"]
    beam = square_beam(200, 100.0, seed=4)
    s = settings_for("exact", fresnel=True)
    a = trace(lat.slab(40.0), beam, Optics(1.60, 1.40, seed=7), s)
    b = trace(lat.slab(40.0), beam, Optics(1.60, 1.40, seed=7), s)
    plain = trace(lat.slab(40.0), beam, Optics(1.60, 1.40, seed=7), settings_for("exact"))
    assert np.array_equal(a.direction, b.direction)
    assert (a.direction[:, 1] < 0).sum() > (plain.direction[:, 1] < 0).sum()


def test_a_thousand_rays_through_a_thick_honeycomb_meet_every_wall_the_independent_tracer_meets():
    """Flat walls do not amplify rounding: through 300 µm of a jittered honeycomb (about 46
    interfaces a ray, grazing chords of lumens among them) every ray meets the same interfaces
    as the independent tracer and leaves within 1e-9 rad.  (Once a chord entered where the
    lumen's g and the phase disagree within rounding was passed over: ray 366 of this beam.)"""
    from pipeline.optics.references import reference

    lat = reference("cells-hex", pitch_um=14.5, wall_um=2.0, jitter=0.1).lattice(1)
    beam = square_beam(1000, 150.0, seed=1, direction=(0.2, 1.0, 0.1))
    march = trace(lat.slab(300.0), beam, Optics(1.52, 1.49), settings_for("exact"))
    ref = lat.trace_independently(beam.origins, beam.unit_directions(), n_wall=1.52, n_poly=1.49, thickness_um=300.0)
    assert np.array_equal(march.events, ref.events)
    assert _angle(march.direction, ref.direction).max() <= 1e-9
