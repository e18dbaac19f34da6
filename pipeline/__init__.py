"""twray: ray scattering in transparent-wood microstructures."""

from ._kernel_cache import configure as _configure_kernel_cache

__version__ = "0.1.0"

_configure_kernel_cache()
