"""Views of a wood volume for people and other programs: PNG slices, TIFF stacks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cache import atomic_write
from .volume import WoodVolume

PLANES = {
    # name: (description, axis held fixed, image axes (rows, columns))
    "RT": ("cross-section (R-T plane) at mid L", 2, ("T", "R")),
    "LT": ("L-T plane at mid R", 0, ("T", "L")),
    "LR": ("L-R plane at mid T", 1, ("R", "L")),
}


def plane(vol: WoodVolume, name: str, index: int | None = None) -> np.ndarray:
    """A mid-plane of the volume as an image (rows, columns) per :data:`PLANES`."""
    _, axis, _ = PLANES[name]
    i = vol.shape[axis] // 2 if index is None else index
    key = [slice(None)] * 3
    key[axis] = i
    img = vol[tuple(key)]
    # RT: rows T, columns R; LT: rows T, columns L; LR: rows R, columns L.
    return img.T if name == "RT" else img


def write_slices(vol: WoodVolume, out: str | Path) -> list[Path]:
    """Write one PNG per plane (1 pixel per voxel, wall black) and an overview with µm axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    v = vol.grid.voxel_um
    written = []
    fig, axes = plt.subplots(1, 3, figsize=(15, 5))
    for ax, (name, (title, _, (rows, cols))) in zip(axes, PLANES.items()):
        img = plane(vol, name)
        path = out / f"slice_{name}.png"
        atomic_write(path, lambda tmp: Image.fromarray(((1 - img) * 255).astype(np.uint8)).save(tmp, format="PNG"))
        written.append(path)
        ax.imshow(img, cmap="gray_r", origin="lower", interpolation="nearest",
                  extent=(0, img.shape[1] * v, 0, img.shape[0] * v))
        ax.set_title(title)
        ax.set_xlabel(f"{cols} [µm]")
        ax.set_ylabel(f"{rows} [µm]")
    fig.suptitle(f"{vol.path.name}: {vol.params.species}, wall black, polymer white")
    fig.tight_layout()
    path = out / "slices.png"
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)
    written.append(path)
    return written


def write_tiff_stack(vol: WoodVolume, out: str | Path) -> list[Path]:
    """One TIFF per L slice (image rows R, columns T), ImageJ metadata in µm."""
    import tifffile

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    res = 1.0 / vol.grid.voxel_um
    paths = []
    width = max(5, len(str(vol.shape[2] - 1)))
    cl = vol.chunks[2]
    for k0 in range(0, vol.shape[2], cl):
        block = vol[:, :, k0:k0 + cl]
        for dk in range(block.shape[2]):
            path = out / f"slice_{k0 + dk:0{width}d}.tif"
            atomic_write(path, lambda tmp: tifffile.imwrite(
                tmp, np.ascontiguousarray(block[:, :, dk]), imagej=True, resolution=(res, res),
                metadata={"unit": "um", "spacing": vol.grid.voxel_um, "axes": "YX"}))
            paths.append(path)
    return paths
