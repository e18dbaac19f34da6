"""The scalar wave solver against analytic optics, and the rays-against-waves map as a cached study."""

import math

import numpy as np
import pytest
from scipy.special import h1vp, hankel1, jv, jvp

from pipeline.params import ParameterError
from pipeline.wave.solver import Sampling, StepReflectance, absorber, gaussian_beam, kx_of, propagate
from pipeline.wave.spectrum import diffraction_limit_deg, exit_angles, power_summary, white_light

LAM = 0.589
K0 = 2 * math.pi / LAM


def _run(levels, sampling, *, dn, n0=1.5, field=None, mean_fraction=0.0, mask=None, k0=K0):
    nx = levels.shape[1]
    u0 = np.ones((1, nx), np.complex64) if field is None else field[None].astype(np.complex64)
    spec, lost = propagate(u0, [levels], k0=np.array([k0]), delta_n=np.array([dn]), n0=np.array([n0]),
                           sampling=sampling, mean_fraction=mean_fraction, mask=mask)
    p = np.abs(spec[0]) ** 2
    return p / p.sum(), lost[0], spec[0]


def _grating(sampling, period, width, levels):
    x = np.arange(int(round(width / sampling.dx_um))) * sampling.dx_um
    return x, np.round((1 + np.cos(2 * np.pi * x / period)) / 2 * levels).astype(np.uint8)


def test_power_is_conserved_but_for_rounding_and_what_goes_evanescent():
    s = Sampling()
    rng = np.random.default_rng(3)
    x = np.arange(1024) * s.dx_um
    z = np.arange(2000)[:, None] * s.dz_um
    f = sum(np.cos(2 * np.pi * (x / rng.uniform(3, 20) + z / rng.uniform(3, 20) + rng.uniform())) for _ in range(6))
    lev = np.round((f - f.min()) / (f.max() - f.min()) * s.levels).astype(np.uint8)  # walls of a few µm
    field = gaussian_beam(x, x.mean(), 40.0)[None]
    k0 = np.array([K0])

    def lost(dn, dtype):
        return propagate(field, [lev], k0=k0, delta_n=np.array([dn]), n0=np.array([1.5]), sampling=s,
                         dtype=dtype)[1][0]

    assert lost(0.0, np.complex128) < 1e-12  # the propagation is unitary
    assert lost(0.0, np.complex64) < 3e-8 * 2000  # single precision rounds away < 3e-8 a step
    assert 0 < lost(0.03, np.complex128) < 1e-3  # the steps of the screen's levels send a little evanescent


def test_thin_sinusoidal_phase_grating_diffracts_as_raman_nath_bessel_squares():
    s = Sampling(sub_um=0.004, per_dx=15, per_dz=17)  # 255 levels: a smooth sinusoid
    period, n_periods = 20.0, 4
    _, lev = _grating(s, period, period * n_periods, 255)
    nz = int(round(1.0 / s.dz_um))
    phi1 = 1.5  # the phase modulation's amplitude [rad]; Q = 2πλd/(nΛ²) = 0.006, deep in Raman-Nath
    dn = 2 * phi1 / (K0 * nz * s.dz_um)
    p, _, _ = _run(np.tile(lev, (nz, 1)), s, dn=dn, mean_fraction=0.5)
    for m in range(4):
        assert p[m * n_periods] == pytest.approx(jv(m, phi1) ** 2, abs=2e-4)
        assert p[-m * n_periods] == pytest.approx(jv(m, phi1) ** 2, abs=2e-4)


def test_thick_grating_at_the_bragg_angle_follows_kogelnik():
    s = Sampling(sub_um=0.005, per_dx=10, per_dz=10)
    period, n = 2.0, 1.5
    x, lev = _grating(s, period, 40.0, 100)
    d = 200.0  # Q = 2πλd/(nΛ²) = 123: one diffracted order
    theta_b = math.asin(LAM / (2 * n * period))
    dn1 = LAM * math.cos(theta_b) / (4 * d)  # Kogelnik: η = sin²(π Δn1 d / (λ cos θB)) = 1/2
    nz = int(round(d / s.dz_um))
    p, _, _ = _run(np.tile(lev, (nz, 1)), s, dn=2 * dn1, n0=n, field=np.exp(1j * math.pi / period * x),
                   mean_fraction=0.5)
    kx = kx_of(x.size, s.dx_um)
    diffracted = p[np.argmin(abs(kx + math.pi / period))]
    assert diffracted == pytest.approx(0.5, abs=0.015)
    assert p[np.argmin(abs(kx - math.pi / period))] + diffracted > 0.995


def _wedge(alpha_deg, dn, w0=20.0):
    """Mean exit direction of a Gaussian beam (along T, in 1.49) refracted into 1.49 + dn at a plane
    interface whose normal is ``alpha_deg`` from T [degree, from kx]."""
    s = Sampling(sub_um=0.02, per_dx=5, per_dz=2)
    a = math.radians(alpha_deg)
    t, width = 2 * 45 * math.tan(a) + 40, 400.0
    x = (np.arange(int(round(width / s.dx_um))) + 0.5) * s.dx_um
    z = (np.arange(int(round(t / s.dz_um))) + 0.5) * s.dz_um
    frac = np.zeros((z.size, x.size))
    for i in range(4):
        for j in range(4):
            zz = z[:, None] + (j - 1.5) / 4 * s.dz_um - t / 2
            xx = x[None, :] + (i - 1.5) / 4 * s.dx_um - width / 2
            frac += (zz * math.cos(a) - xx * math.sin(a)) > 0
    lev = np.round(frac / 16 * s.levels).astype(np.uint8)
    p, _, _ = _run(lev, s, dn=dn, n0=1.49, field=gaussian_beam(x, width / 2, 2 * w0), mask=absorber(x.size, s.dx_um))
    kx = kx_of(x.size, s.dx_um)
    return -math.degrees(math.asin((p * kx).sum() / (K0 * (1.49 + dn))))


@pytest.mark.parametrize("alpha, dn, tol", [(30, 0.03, 0.005), (60, 0.03, 0.03), (60, -0.03, 0.03)])
def test_tilted_interface_refracts_by_snell_and_reflects_little(alpha, dn, tol):
    a = math.radians(alpha)
    n1, n2 = 1.49, 1.49 + dn
    b = math.asin(n1 * math.sin(a) / n2)
    assert _wedge(alpha, dn) == pytest.approx(math.degrees(a - b), rel=tol)
    r_te = ((n1 * math.cos(a) - n2 * math.cos(b)) / (n1 * math.cos(a) + n2 * math.cos(b))) ** 2
    assert r_te < 2e-3  # what the forward solver leaves out at this interface


def test_step_reflectance_counts_both_faces_of_every_wall_across_blocks():
    s = Sampling()
    lev = np.zeros((400, 3), np.uint8)
    lev[100:150] = s.levels  # one wall, its far face in the second block
    lev[300:301, 0] = s.levels  # a thin one in one column only
    tracker = StepReflectance([lev[:120], lev[120:]], s.levels)
    assert sum(b.shape[0] for b in tracker) == 400
    r2 = (0.03 / (2 * 1.49)) ** 2
    assert tracker.reflectance(0.03, 1.49) == pytest.approx(r2 * (2 + 2 / 3))


def test_a_cylinder_scatters_as_its_exact_series():
    """A dielectric cylinder (radius 2 µm, ΔRI 0.02) in a plane wave: the scattered far field
    |T(φ)| = |Σ b_m e^{imφ}| of the exact scalar series, against the solver's |A(k sin φ)| k cos φ / 2,
    A the continuous Fourier transform of the scattered field at the exit plane."""
    s = Sampling(sub_um=0.01, per_dx=5, per_dz=3)
    a, n1, dn = 2.0, 1.49, 0.02
    width, depth = 80.0, 2 * a + 4.0
    x = (np.arange(int(round(width / s.dx_um))) + 0.5) * s.dx_um
    nz = int(round(depth / s.dz_um))
    z = (np.arange(nz) + 0.5) * s.dz_um
    frac = np.zeros((nz, x.size))
    for i in range(s.per_dx):
        for j in range(s.per_dz):
            xx = x[None, :] + ((i + 0.5) / s.per_dx - 0.5) * s.dx_um - width / 2
            zz = z[:, None] + ((j + 0.5) / s.per_dz - 0.5) * s.dz_um - depth / 2
            frac += xx ** 2 + zz ** 2 < a * a
    _, _, spec = _run(frac.astype(np.uint8), s, dn=dn, n0=n1)
    u = np.fft.ifft(spec)
    # the free wave picks up nothing (carrier removed), so the scattered field is u - 1
    big = np.fft.fft(u - 1.0) * s.dx_um
    kx = kx_of(x.size, s.dx_um)
    k1 = K0 * n1
    phi = np.radians(np.arange(2.0, 26.0, 2.0))
    wave = np.interp(k1 * np.sin(phi), np.fft.fftshift(kx), np.fft.fftshift(np.abs(big))) * k1 * np.cos(phi) / 2
    xk, m_r = k1 * a, (n1 + dn) / n1
    m = np.arange(-40, 41)[:, None]
    b = (m_r * jvp(m, m_r * xk) * jv(m, xk) - jvp(m, xk) * jv(m, m_r * xk)) / (
        h1vp(m, xk) * jv(m, m_r * xk) - m_r * jvp(m, m_r * xk) * hankel1(m, xk))
    series = np.abs(np.sum(b * np.exp(1j * m * phi[None, :]), axis=0))
    # within 3.5 % and the screen's 1 - cos φ for a wave at φ (6 % at 20°): the stated error
    assert np.all(np.abs(wave - series) <= (1 - np.cos(phi) + 0.035) * series + 0.01 * series.max())


def test_an_empty_window_transmits_the_beam_at_its_diffraction_limit():
    s = Sampling()
    x = (np.arange(4096) + 0.5) * s.dx_um
    lev = np.zeros((50, x.size), np.uint8)
    p, lost, spec = _run(lev, s, dn=0.01, n0=1.49, field=gaussian_beam(x, x.mean(), 100.0),
                         mask=absorber(x.size, s.dx_um))
    big = np.fft.fft(np.fft.ifft(spec), n=4 * x.size)[None]
    theta, power = exit_angles(big, kx_of(4 * x.size, s.dx_um), np.array([K0]), np.array([1.49]), "internal")
    out = power_summary(theta[0], power[0], n_rays=1e9)  # a kernel of nothing: the bare spectrum
    assert lost < 1e-5  # rounding in single precision
    assert out["haze"] < 1e-6
    assert out["half-max"] == pytest.approx(diffraction_limit_deg(LAM, 1.49, 100.0), rel=0.02)


def test_white_light_weights_the_eye_and_illuminant_c():
    lam = white_light(5)
    assert np.all(np.diff(lam) > 0) and 0.45 < lam[0] and lam[-1] < 0.66
    assert lam[2] == pytest.approx(0.56, abs=0.01)  # the median of illuminant C x ybar
    with pytest.raises(ValueError, match="wavelengths"):
        white_light(0)


def test_sampling_refuses_steps_that_cannot_carry_the_angles():
    with pytest.raises(ParameterError, match=r"dx = 0.3 µm, more than λ/\(2n\)"):
        Sampling(sub_um=0.1, per_dx=3).validate(0.45, 1.5)
    with pytest.raises(ParameterError, match="sampling.per_dz"):
        Sampling(per_dz=0).validate(0.45, 1.5)
