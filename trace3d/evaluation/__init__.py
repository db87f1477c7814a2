"""Evaluation: 3D object extraction (Table 2) and novel-view 2D segmentation (Tables 3 and 4).

metrics.py      IoU, accuracy / precision, PSNR in the grown ground-truth box
groundtruth.py  the evaluated objects, their masks, which views count, the reference view, queries
extraction.py   render the object's Gaussians alone: IoU of their footprint, PSNR of their colours
nvs.py          the lifted scene's masks at test views: IoU and mAcc
pictures.py     a figure per scene; multi-view renders of each extracted object
step.py         the ``evaluate`` step (``metrics.json``, ``pictures.png``, ``objects/``)

Evaluation only talks to a :class:`~trace3d.lifting.LiftedScene`; see docs/evaluation.md.
"""
