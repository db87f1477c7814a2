"""trace3d: consistent 2D-segmentation lifting into 2D Gaussian Splatting scenes (Trace3D, ICCV 2025)."""

__version__ = "0.1.0"
