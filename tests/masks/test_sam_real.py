"""The ``sam`` mask source against the real ``segment-anything`` package (the code path, not mask quality).

Installs nothing: it runs when ``segment_anything`` (and the ``torchvision`` it imports) can be imported
(``pip install -e .[sam-test]``), and skips naming what is missing otherwise. No weights are downloaded: a
randomly initialised ViT-B (``sam_model_registry["vit_b"](checkpoint=None)``) is saved as the checkpoint,
so the masks are noise; what is checked is that ``trace3d masks --source sam`` loads the checkpoint, runs
the automatic mask generator on every view and writes masks in the step's format. SAM resizes every image
to 1024 on its longer side, so each view costs one ViT-B forward at 1024 x 1024 on the CPU whatever the
scene's size: about 21 CPU-seconds per view on 2 threads (measured: docs/masks.md, "SAM").
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from trace3d.cli import main as cli_main
from trace3d.scene import Scene

pytestmark = pytest.mark.slow


def _segment_anything():
    try:
        import segment_anything
    except ImportError as exc:  # the package, or torchvision which it imports
        pytest.skip(f"segment-anything is not importable ({exc}); `pip install -e .[sam-test]` installs it with "
                    "torchvision (the build matching the installed torch)")
    except RuntimeError as exc:  # a torchvision built for another torch fails while registering its operators
        pytest.skip(f"segment-anything's torchvision does not load against this torch ({exc}); install the "
                    "torchvision build matching the installed torch")
    return segment_anything


def test_sam_source_runs_the_real_generator_on_a_tiny_scene(tmp_path):
    segment_anything = _segment_anything()
    import torch

    from trace3d.datasets.synthetic.params import SyntheticParams
    from trace3d.datasets.synthetic.writer import generate_scene
    from trace3d.masks import read_mask_npz

    torch.manual_seed(0)
    model = segment_anything.sam_model_registry["vit_b"](checkpoint=None)
    checkpoint = tmp_path / "sam_vit_b_random.pth"
    torch.save(model.state_dict(), checkpoint)
    generate_scene(tmp_path / "scene", SyntheticParams(seed=4, width=48, height=32, num_views=2, test_every=2,
                                                       supersample=1))
    scene = Scene.read(tmp_path / "scene")
    # random weights predict random IoUs and stabilities: keep every mask so that the format has something to show
    params = {"checkpoint": str(checkpoint), "model_type": "vit_b", "points_per_side": 4, "points_per_batch": 16,
              "pred_iou_thresh": 0.0, "stability_score_thresh": 0.0, "max_small_pixels": 0}
    out = tmp_path / "masks"
    assert cli_main(["masks", "--scene", str(tmp_path / "scene"), "--source", "sam", "--params", json.dumps(params),
                     "--out", str(out)]) == 0
    summary = json.loads((out / "masks.json").read_text())
    assert summary["source"] == "sam" and summary["params"]["model_type"] == "vit_b"
    assert set(summary["masks_per_view"]) == {c.name for c in scene.cameras} and summary["total_masks"] > 0
    for cam in scene.cameras:
        masks, scores = read_mask_npz(out / f"{cam.name}.npz", cam.height, cam.width)
        assert masks.dtype == bool and masks.shape[1:] == (cam.height, cam.width)
        assert scores.dtype == np.float32 and scores.shape == (len(masks),)
        areas = masks.reshape(len(masks), -1).sum(axis=1)
        assert np.all(np.diff(areas) >= 0)  # the post-processing's order: smallest first
        assert summary["masks_per_view"][cam.name] == len(masks)


def test_sam_source_refuses_a_missing_checkpoint_in_one_sentence(tmp_path, capsys):
    _segment_anything()
    from trace3d.datasets.synthetic.params import SyntheticParams
    from trace3d.datasets.synthetic.writer import generate_scene

    generate_scene(tmp_path / "scene", SyntheticParams(seed=4, width=32, height=24, num_views=2, test_every=2,
                                                       supersample=1))
    params = json.dumps({"checkpoint": str(tmp_path / "nowhere.pth"), "model_type": "vit_b"})
    out = tmp_path / "masks"
    assert cli_main(["masks", "--scene", str(tmp_path / "scene"), "--source", "sam", "--params", params,
                     "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "nowhere.pth does not exist" in err and "Traceback" not in err
    assert not out.exists()
