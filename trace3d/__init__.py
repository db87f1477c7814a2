"""trace3d: consistent 2D-segmentation lifting into 2D Gaussian Splatting scenes (Trace3D, ICCV 2025)."""

import os as _os

# Idle OpenMP threads of torch spin and steal the cores numba's kernels need (about 2x slower
# forward+backward on 2 busy cores); let them sleep unless the user chose otherwise.  This must
# run before torch is imported, which is why it lives in the package's __init__.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
