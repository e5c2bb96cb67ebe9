"""``crisp reconstruct-all``: a folder of inputs reconstructed on a local Ray cluster of 2 workers;
each clip is the one ``crisp reconstruct`` writes for that input alone, and a broken input is
reported without stopping the others."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("ray")

from crisp_gym.clip import load_clip_dir  # noqa: E402
from crisp_gym.reconstruct import batch, pipeline  # noqa: E402
from crisp_gym.registry import list_clips  # noqa: E402
from tests.conftest import small_synth_input  # noqa: E402


def test_a_folder_of_inputs_becomes_clips_on_two_ray_workers(tmp_path, capsys):
    inputs = tmp_path / "inputs"
    for kind, seed in (("platform_step", 5), ("stairs_up", 3)):
        small_synth_input(inputs / kind, kind, seed)
    (inputs / "broken").mkdir()
    (inputs / "broken" / "input.npz").write_bytes(b"not an archive")
    assert [name for name, _, _ in batch.find_inputs(inputs)] == ["broken", "platform_step", "stairs_up"]

    code = batch.main([str(inputs), "-o", str(tmp_path / "clips"), "--num-cpus", "2", "--register"])
    out = capsys.readouterr().out
    assert code == 2 and "wrote 2 of 3 clips" in out and "broken: ValueError" in out
    for kind in ("platform_step", "stairs_up"):
        clip = load_clip_dir(tmp_path / "clips" / kind)
        alone = load_clip_dir(pipeline.run(pipeline.ReconstructArgs(
            input=inputs / kind / "input.npz", motion=inputs / kind / "motion_camera.npz",
            output=tmp_path / "alone" / kind)))
        assert len(clip.boxes) == len(alone.boxes)
        np.testing.assert_allclose([b.center for b in clip.boxes], [b.center for b in alone.boxes], atol=1e-9)
        np.testing.assert_allclose(clip.motion.root_pos, alone.motion.root_pos, atol=1e-9)
    assert {"platform_step", "stairs_up"} <= set(list_clips()) and "broken" not in list_clips()
