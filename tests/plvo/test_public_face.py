"""The library's public face (plvo/__init__.py): the README's three lines run a sequence, every public name is the
module's own object, and `import plvo` alone loads none of the pipeline's libraries."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest


def test_the_readme_example_runs_a_sequence(synth_sequence_factory):
    import plvo

    dataset = plvo.open_dataset(synth_sequence_factory(12, seed=0), "00")
    out = plvo.run_dataset(dataset, plvo.load_config(None))
    assert isinstance(out, plvo.RunOutput)
    assert out.poses.shape == (12, 4, 4)
    np.testing.assert_allclose(out.poses[0], np.eye(4), atol=1e-9)  # cam0 of the first frame
    gt = np.asarray(dataset.gt_T_world_cam, float)
    gt = np.linalg.inv(gt[0]) @ gt
    assert np.linalg.norm(out.poses[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.1  # tracked, not a stub


def test_every_public_name_is_its_module_own():
    import importlib

    import plvo

    assert sorted(plvo._PUBLIC) == plvo.__all__
    for name, module in plvo._PUBLIC.items():
        assert getattr(plvo, name) is getattr(importlib.import_module(module), name), name
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        plvo.nothing  # noqa: B018


def test_import_plvo_loads_no_pipeline_library():
    loaded = subprocess.run(
        [sys.executable, "-c", "import sys, plvo; print(sorted(m for m in ('numpy', 'cv2', 'open3d', 'gtsam', "
                               "'plvo.runtime.system') if m in sys.modules))"],
        capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "[]", loaded
