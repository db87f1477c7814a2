"""The build and run tools around the pipeline, not stages of it.

    codehash.py              each step's code version from the import graph; the keyed numba cache folder
    compiling.py             the compile listener: numba compile seconds per step, the cache folder check
    cputarget.py             the numba CPU target (512-bit vectors on AVX-512 CPUs), set by the entry points
    schema.py                the steps' parameter schema (workflow/schemas/steps.schema.yaml), ``--help`` listings
    warm.py                  fill the numba cache at the recorded signatures (``python -m trace3d.tooling.warm``)
    kernel_signatures.json   those signatures, recorded from a test run (``warm --record``)
"""
