"""Scalar wave optics on twray's media: where geometrical optics holds (docs/methods.md#wave-optics).

``solver`` propagates a field along T through a refractive-index map by multi-slice angular
spectrum steps; ``sections`` samples the map from the model's own phase (reference lattices and
wood sections uniform along L); ``spectrum`` turns exit fields into angular power, haze and widths
by the rays' estimators; ``regime`` runs rays and waves on the same cases as a cached Dask graph
and writes the map as a Dataset.
"""
