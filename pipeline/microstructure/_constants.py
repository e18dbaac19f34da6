"""Constants of the microstructure model's kernels: the layout of the model-constant vector
``M``, the fixed structure of the stationary layouts, and the cost counters
(docs/methods.md#the-microstructure-model)."""

import numpy as np

# Indices into the model-constant vector ``M`` (float64).  Lengths in µm.
PITCH, SCALE, T0, WALLVAR, JITTER, PUSH, CTRL, FLEN, FLEN_SD, PLATE, ENDS, SHAPE = range(12)
VESSELS, VPROB, VPAIR, VTRIPLE, VWALL = range(12, 17)
RAYS, RSPACE, RJIT, RSER, RWIDTH, RHEIGHT, RLEN, RLEN_SD, RGROUP, RGROUP_SD, RSQUEEZE, RRAMP = range(17, 29)
DIST, LARGE_P, BEND_A, BEND_WL, TIP = range(29, 34)
N_CONSTANTS = 34

WALL = np.uint8(1)
POLYMER = np.uint8(0)

# Fixed structure of the stationary layouts (in lattice nodes / cell heights).
VTILE_R = 12  # vessel tile size along R [nodes]
VTILE_T = 10  # ... along T [nodes]
VHARD_R = 8  # hard-core box between vessels of different clusters [nodes]
VHARD_T = 8  # also keeps the lookup cells of two clusters apart
VRAY_CLEAR = 5  # vessels stay this many nodes away from ray rows
VESSEL_AXIS_R = 3.2 / 3.0  # outline semi-axis along R relative to the 3-node span
RAY_PERIOD = 26  # L slot per ray group [cell heights]; one group per slot
RAY_MIN_GAP = 6  # minimum gap between groups [cell heights]
GRID_PER_PITCH = 8  # distortion grid nodes per lattice pitch
TILE = 64  # distortion grid cells per tile side

# Stats counters (a cost model: equal counters mean equal work).
ST_NODES, ST_VOXELS, ST_DIPOLES, ST_LATTICE, ST_TILES = range(5)
