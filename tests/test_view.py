"""``crisp view``: the viewer's scene follows the tracks on its timeline, and a real browser
(headless Chromium, software WebGL) draws it."""

from __future__ import annotations

import shutil
import socket
import subprocess

import imageio.v3 as iio
import numpy as np
import pytest

viser = pytest.importorskip("viser")

from crisp_gym.humanoid import BODY_NAMES  # noqa: E402
from crisp_gym.registry import load_clip  # noqa: E402
from crisp_gym.train.view import (  # noqa: E402
    REFERENCE_RGB,
    SIMULATED_RGB,
    ViewArgs,
    Viewer,
    policy_and_clip,
    policy_track,
    reference_track,
)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def walk():
    clip = load_clip("flat_walk")
    policy, clip_name = policy_and_clip(ViewArgs(source="assets/policies/flat_walk"))
    assert clip_name == "flat_walk" and policy is not None  # a policy file's own training clip
    return clip, reference_track(clip), policy_track(policy, clip.path)


def test_the_timeline_poses_every_humanoid_body(walk):
    clip, reference, rollout = walk
    assert rollout.body_pos.shape == reference.body_pos.shape  # the shipped policy tracks the whole clip
    server = viser.ViserServer(port=_free_port(), verbose=False)
    try:
        viewer = Viewer(server, clip.boxes, {"reference": (reference, REFERENCE_RGB, 0.45),
                                             "policy": (rollout, SIMULATED_RGB, 1.0)})
        for frame in (0, 60, len(reference.body_pos) - 1):
            viewer.slider.value = frame  # as a user drags it: the callback poses the bodies
            for name, track in (("reference", reference), ("policy", rollout)):
                for body in ("Pelvis", "L_Toe", "R_Hand"):
                    handle, index = viewer.frames[name, body], BODY_NAMES.index(body)
                    np.testing.assert_allclose(handle.position, track.body_pos[frame, index], atol=1e-6)
                    np.testing.assert_allclose(np.abs(handle.wxyz @ track.body_quat[frame, index]), 1.0, atol=1e-6)
    finally:
        server.stop()


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (scripts/install.sh installs it)")
def test_a_browser_draws_the_scene_and_the_humanoids(walk, tmp_path):
    clip, reference, rollout = walk
    port = _free_port()
    server = viser.ViserServer(port=port, verbose=False)
    try:
        Viewer(server, clip.boxes, {"reference": (reference, REFERENCE_RGB, 0.45),
                                    "policy": (rollout, SIMULATED_RGB, 1.0)})
        shot = tmp_path / "view.png"
        software_webgl = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        # The screenshot is taken when the page's virtual time runs out, and virtual time does not
        # wait for the scene arriving over the websocket: on a loaded machine the first page can
        # be drawn before the humanoids reach it (63 of the >300 pixels once in CI), so a fresh
        # page gets up to three tries, each with more virtual time.
        for budget_ms in (8000, 16000, 32000):
            subprocess.run([CHROMIUM, "--headless", "--no-sandbox", *software_webgl,
                            f"--virtual-time-budget={budget_ms}", "--window-size=1000,700", f"--screenshot={shot}",
                            f"http://127.0.0.1:{port}"], capture_output=True, timeout=120, check=True)
            image = iio.imread(shot)[..., :3].astype(int)
            orange = (np.abs(image - SIMULATED_RGB).max(axis=-1) < 60) & (image[..., 0] > image[..., 2] + 40)
            if orange.sum() > 300:
                break
    finally:
        server.stop()
    assert orange.sum() > 300  # the simulated humanoid is drawn (not only the page around the canvas)
    assert image[100:600, 100:900].std() > 10


def test_the_input_point_cloud_lands_on_the_reconstructed_scene(tmp_path):
    """``--points``: the clip's input depth, scaled and aligned as ``meta.json`` says, lies on the
    primitives fitted to it (a wrong scale or transform would put it metres away)."""
    from crisp_gym.clip import load_clip_dir
    from crisp_gym.metrics import box_signed_distance
    from crisp_gym.reconstruct import pipeline
    from crisp_gym.train.view import input_points
    from tests.conftest import small_synth_input

    source = small_synth_input(tmp_path / "input", "stairs_up", 3)
    out = pipeline.run(pipeline.ReconstructArgs(input=source / "input.npz", motion=source / "motion_camera.npz",
                                                output=tmp_path / "clip", contacts="none"))
    clip = load_clip_dir(out)
    points = input_points(clip, max_points=5000)
    assert points.shape == (5000, 3)
    path = clip.motion.root_pos[:, :2]  # the fit keeps what lies within 2.5 m of the person's path
    close = np.min(np.linalg.norm(points[:, None, :2] - path[None], axis=-1), axis=1) < 2.0
    distance = np.abs(box_signed_distance(points[close], clip.boxes))
    assert close.mean() > 0.3 and np.median(distance) < 0.03
