"""trace3d: consistent 2D-segmentation lifting into 2D Gaussian Splatting scenes (Trace3D, ICCV 2025).

Importing the package changes nothing in the process (no environment variables, no threads): the
settings that make the CPU kernels fast (``OMP_WAIT_POLICY=PASSIVE``, a numba cache folder, 512-bit
vectors on AVX-512 CPUs: :mod:`trace3d.tooling.cputarget`) are made by the entry points — ``trace3d``
(:func:`trace3d.cli.main`), the Makefile, the Snakemake rules (``rules/common.smk``) and
``tests/conftest.py``; in a notebook, set them in the environment before starting Python, or call
:func:`trace3d.tooling.cputarget.set_wide_vectors` before importing numba (see docs/performance.md).
"""

__version__ = "0.1.0"
