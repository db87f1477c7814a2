"""2D Gaussian splatting rasterizer (2DGS): projection in torch, CPU tile kernels in numba with a
hand-written backward, a dense pure-torch reference twin, and Gaussian Instance Tracing (GIT).

Public API::

    from trace3d.render import Splats, RenderOutput, render, trace, trace_argmax, trace_reduced
"""

from .core import (BACKENDS, RenderOutput, render, set_default_backend, trace, trace_argmax,
                   trace_by_backward, trace_reduced)
from .kernels.rasterize import GRADIENT_BUFFERS, gradient_buffer_count, gradient_buffers
from .projection import Projected, Splats, project, quat_to_rotmat

__all__ = [
    "BACKENDS", "GRADIENT_BUFFERS", "Projected", "RenderOutput", "Splats", "project", "quat_to_rotmat", "render",
    "gradient_buffer_count", "gradient_buffers", "set_default_backend", "trace", "trace_argmax", "trace_by_backward",
    "trace_reduced",
]
