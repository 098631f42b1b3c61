"""Defaults shared by the API and the command line: each stated once here (kept import-light)."""

DEFAULT_REGIONS = "upper-lower"  # brows + eyes / mouth + jaw (schemes.resolve_regions)
DEFAULT_N_KEYS = 8  # key shapes per region (keyshapes.find_keyshapes)
DEFAULT_METHOD = "spa"  # successive projection (keyshapes.find_keyshapes)
MAX_ERROR = 2.0  # % of the inter-ocular distance: the default target of n_keys="auto"
MAX_KEYS = 24  # default cap of n_keys="auto" per region: a sculpt list an artist can still make
DEFAULT_SMOOTHNESS = 0.1  # zero-lag temporal smoothness of the solve (decompose.solve_weights)
DEFAULT_UPPER = 1.0  # upper bound of every key weight
DEFAULT_MIRROR = True  # add each key's left-right mirror where it adds reach (keyshapes.add_mirrors)
MIRROR_SUFFIX = "_mirror"  # a mirrored key is named f"{source}{MIRROR_SUFFIX}" (keyshapes, targets)
FRONTS = ("auto", "+z", "-z", "+x", "-x", "+y", "-y")  # the axis a character faces (targets.find_correspondence)
