"""CPU tile kernels (numba) for 2DGS blending, their hand-written backward, and GIT tracing.

    tiles.py            tile size, the input layout (``pack_geometry``), fast-math flags, and the per-lane
                        evaluation that forward, backward and trace share (:func:`~.tiles.eval_lane`), so
                        that they make bit-identical decisions for every pixel-splat pair
    binning.py          the depth order (radix argsort), tile lists, row gather/scatter, ``Binning``
    forward.py          front-to-back blending (``forward_kernel``)
    backward.py         its hand-written backward, the chunk sum, the background's share
    backward_values.py  the values-only backward (frozen geometry)
    trace.py            GIT: per splat and label, the weight sums (``trace_kernel``, ``trace_triplets``)
    coalesce.py         the trace's triplets as a sparse matrix and its per-splat argmax
    rasterize.py        the autograd Function and ``rasterize``, what :func:`trace3d.render.render` calls
    glue.py             the per-Gaussian kernels around the tiles: camera points, splat frames, SH colours

(This package was ``render/kernels.py`` and ``render/glue_kernels.py``; every definition moved
unchanged.)  Numba's cache does not see changes in another file (``tiles.py``, ``binning.py``, ``glue.py``,
the thresholds in ``render/projection.py``); the entry points key the cache folder by the kernels' whole
import closure instead (:func:`trace3d.tooling.codehash.key_numba_cache`, docs/architecture.md).

Kernel boundary (small on purpose, so that a CUDA back end can slot in behind it): per splat the
kernels read

    geom [N, 16] float32: A (3), B (3), D (3) with c = A + x B + y D; T_w (3); means2d (2);
                          opacity (1); ln(255 o) (1, informational: pads a row to 64 bytes)
    vals [N, K]  float32: per-splat constant channels (features, then the normal)

(rows gathered into tile-list order before the kernels run) and produce per pixel the blended
channels [H, W, K], sum w z, sum w (z - z_ref)^2, the final transmittance and the median depth.
The backward returns gradients with respect to ``geom``'s first 15 columns and ``vals``; autograd
carries them back through the torch projection to the 3D parameters.

Scheme (as in the CUDA rasterizers): splats are binned to 16x16 tiles (each tile's list in
front-to-back order of centre depth, ties by index), a tile's pixels are blended front to back,
splat by splat: for each row of the splat's footprint box inside the tile, pass 1 evaluates all
16 lanes of the row branch-free (vectorised, with :func:`exp_neg`), pass 2 blends the lanes inside
the box.  Forward, backward and trace share :func:`eval_lane`, so they make bit-identical skip
decisions.  The backward walks each tile's list
back to front, recovering the transmittance by division and keeping, per pixel, the running
"what comes after" dot product.  Tiles run in parallel (``prange``); gradients go to one buffer per
worker chunk (tiles are dealt round-robin to chunks), summed afterwards: race-free and
deterministic.  When nothing upstream of the geometry needs a gradient (lifting's frozen scene, GIT
through autograd), :func:`backward_values_kernel` does the same walk for the value gradients alone.
"""
