"""The HTML pages of ``crisp reconstruct``, ``crisp eval`` and ``crisp gap diagnose``, opened in a
real headless browser (Chromium from Debian's packages, installed by ``scripts/install.sh``): each
page's plots and video load, and its screenshot shows them."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from crisp_gym.reconstruct import pipeline
from crisp_gym.sim2real.diagnose import DiagnoseConfig, diagnose
from crisp_gym.sim2real.report import write_report
from tests.conftest import small_synth_input
from tests.test_sim2real_diagnose import _case as servo_case

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (scripts/install.sh installs it)")
SHIPPED = Path(__file__).resolve().parents[1] / "assets" / "policies" / "flat_walk"


def open_in_browser(page: Path, tmp_path: Path) -> tuple[dict[str, tuple[int, int]], list[np.ndarray]]:
    """(loaded / total images and videos as the page's own script counted them, the screenshot's
    crop of every image the browser drew within its 1200 x 4000 window)."""
    flags = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
             "--virtual-time-budget=8000", "--window-size=1200,4000", "--force-device-scale-factor=1"]
    dom = subprocess.run([*flags, "--dump-dom", page.resolve().as_uri()], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    body = re.search(r"<body([^>]*)>", dom).group(1)
    counts = {kind: tuple(int(n) for n in re.search(rf'data-{kind}="(\d+)/(\d+)"', body).groups())
              for kind in ("images", "videos")}
    boxes = [tuple(int(v) for v in box.split(","))
             for box in re.search(r'data-image-boxes="([^"]*)"', body).group(1).split(";") if box]
    shot = tmp_path / f"{page.parent.name}.png"
    subprocess.run([*flags, f"--screenshot={shot}", page.resolve().as_uri()], capture_output=True, timeout=120,
                   check=True)
    image = iio.imread(shot)[..., :3]
    crops = [image[y:y + h, x:x + w] for x, y, w, h in boxes if y + h <= image.shape[0] and w > 0 and h > 0]
    return counts, crops


def _all_loaded(counts: dict[str, tuple[int, int]], images: int, videos: int) -> None:
    assert counts["images"] == (images, images), counts
    assert counts["videos"] == (videos, videos), counts


def _drawn(crops: list[np.ndarray], images: int) -> None:
    """Every image is in the screenshot and is a picture, not an empty box: lines or shading
    over at least 2 % of its area."""
    assert len(crops) == images
    for crop in crops:
        assert (np.abs(crop.astype(float) - np.median(crop, axis=(0, 1))).max(axis=-1) > 40).mean() > 0.02


def test_eval_page_shows_its_plots_and_rollout(tmp_path):
    from crisp_gym.train.evaluate import main

    out = tmp_path / "eval"
    assert main([str(SHIPPED), "--clip", "flat_walk", "-o", str(out), "--episodes", "2"]) == 0
    counts, crops = open_in_browser(out / "report.html", tmp_path)
    _all_loaded(counts, images=2, videos=1)
    _drawn(crops, images=2)


def test_reconstruct_page_shows_the_clip(tmp_path):
    source = small_synth_input(tmp_path / "input", "platform_step", 5)
    out = pipeline.run(pipeline.ReconstructArgs(input=source / "input.npz", motion=source / "motion_camera.npz",
                                                output=tmp_path / "clip"))
    counts, crops = open_in_browser(out / "report.html", tmp_path)
    _all_loaded(counts, images=1, videos=0)
    _drawn(crops, images=1)
    assert "scale" in (out / "report.html").read_text()


def test_gap_page_shows_the_diagnosis_and_its_plots(tmp_path):
    truth = {"family": "delay", "effect": "actuator_delay", "joint": None, "x": [0.02], "x0": [0.01]}
    sc, train, test = servo_case(truth, seed=5)
    result = diagnose([(train, sc.model)], [(test, sc.model)], DiagnoseConfig(show_progress=False))
    out = write_report(result, tmp_path / "gap")
    counts, crops = open_in_browser(out / "report.html", tmp_path)
    figures = len(re.findall(r"!\[[^\]]*\]\([^)]+\.png\)", (out / "report.md").read_text()))
    assert figures >= 2
    _all_loaded(counts, images=figures, videos=0)
    _drawn(crops, images=figures)
    assert "Verdict" in (out / "report.html").read_text()
