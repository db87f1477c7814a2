"""Trace3D's own stages: Gaussian Instance Tracing, consistent instance maps, GIT-guided density control.

    git.py     trace every training view's label map through the fitted scene; [N, L] argmax statistics
    merge.py   patch similarity by majority vote over co-visible views; consistent instance maps
    refine.py  ambiguity score, split / prune while retraining (a density-control strategy)
"""
