"""twray: ray scattering in transparent-wood microstructures."""

__version__ = "0.1.0"
