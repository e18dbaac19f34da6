"""twray: ray scattering in transparent-wood microstructures."""

from ._kernel_cache import configure as _configure_kernel_cache
from ._numba_inline import install as _install_inliner

__version__ = "0.1.0"

_configure_kernel_cache()
_install_inliner()
