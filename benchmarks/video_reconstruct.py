"""The plain-video path on the real phone video: time per stage and the fidelity of the clip.

Inputs, all made from ``../shared/data/videomimic_sitting`` (127 frames at 15 fps, 540×960: a
person walks in, sits on a low half-log whose top is 0.23-0.25 m above the ground, stands up):

* ``folder``: the image folder as it is (a handheld phone: the camera moves 6 cm, turns 4.6°);
* ``mp4``: the same frames encoded as H.264;
* ``tripod``: every frame warped onto the first by the homography of its background (ORB
  features off the person, RANSAC), so the camera stands still: the path must notice that SfM
  has no parallax and build the scene from the person alone.

Figures per input: wall time and seconds per stage; whether the camera was solved or fixed; the
ground under the planted feet (sole height above the highest box top under it, median and p90 over
planted frames); the seat (the highest box top under the seated pelvis, against the log's
0.23-0.25 m); above that top, the seated humanoid's hip joints' midpoint (where MediaPipe's hip
landmarks are), its pelvis joint (7.6 cm above the hip joints in this humanoid) and its body's
underside; the camera's height, the stature MediaPipe's body size implies and the metrology check
of the scale (:mod:`crisp_gym.reconstruct.body_scale`); and whether ``gym.make("CrispTrack-v0", clip=...)``
loads the clip. Usage::

    python benchmarks/video_reconstruct.py [--inputs folder mp4 tripod] [--out runs/bench_video]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import gymnasium as gym
import imageio.v3 as iio
import numpy as np

import crisp_gym  # noqa: F401 - registers CrispTrack-v0
from crisp_gym.clip import load_clip_dir
from crisp_gym.humanoid import BODY_NAMES, build_humanoid
from crisp_gym.metrics import sole_points, support_tops
from crisp_gym.motion import compute_kinematics, planted_feet
from crisp_gym.reconstruct.io import read_video
from crisp_gym.reconstruct.pipeline import ReconstructArgs, run
from crisp_gym.reconstruct.video import seated_underside

VIDEO = Path(__file__).resolve().parents[2] / "shared" / "data" / "videomimic_sitting"
FPS = 15.0
LOG_TOP = (0.23, 0.25)


def stabilised(frames: np.ndarray) -> np.ndarray:
    """Each frame warped onto the first by a RANSAC homography of ORB matches (a tripod's view)."""
    orb = cv2.ORB_create(4000)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    gray0 = cv2.cvtColor(frames[0], cv2.COLOR_RGB2GRAY)
    kp0, des0 = orb.detectAndCompute(gray0, None)
    out = [frames[0]]
    for frame in frames[1:]:
        kp, des = orb.detectAndCompute(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), None)
        matches = matcher.match(des, des0)
        src = np.float32([kp[m.queryIdx].pt for m in matches])
        dst = np.float32([kp0[m.trainIdx].pt for m in matches])
        homography, _ = cv2.findHomography(src, dst, cv2.RANSAC, 2.0)
        out.append(cv2.warpPerspective(frame, homography, frame.shape[1::-1], borderMode=cv2.BORDER_REFLECT))
    return np.stack(out)


def make_inputs(names: list[str], folder: Path) -> dict[str, Path]:
    frames, _ = read_video(VIDEO, fps=FPS, progress=False)
    inputs: dict[str, Path] = {}
    for name in names:
        if name == "folder":
            inputs[name] = VIDEO
        elif name == "mp4":
            inputs[name] = folder / "videomimic_sitting.mp4"
            iio.imwrite(inputs[name], frames, fps=FPS, codec="libx264", macro_block_size=1, quality=9)
        elif name == "tripod":
            inputs[name] = folder / "tripod"
            inputs[name].mkdir(exist_ok=True)
            for k, frame in enumerate(stabilised(frames)):
                iio.imwrite(inputs[name] / f"{k:05d}.jpg", frame, quality=95)
        else:
            raise SystemExit(f"unknown input {name!r}")
    return inputs


def highest_top(xy: np.ndarray, boxes) -> np.ndarray:
    """(N,) height of the highest box top under each point (-inf where no box is under it)."""
    tops = support_tops(xy, boxes)
    return np.where(np.isnan(tops), -np.inf, tops).max(axis=1)


def fidelity(clip_dir: Path) -> dict:
    clip = load_clip_dir(clip_dir)
    model = build_humanoid()
    motion = clip.motion
    planted = planted_feet(motion, model)
    soles = sole_points(model, motion.qpos())  # (T, 4, 3): L heel, L toe, R heel, R toe
    gaps = []
    for k, side in enumerate((0, 2)):
        for t in np.flatnonzero(planted[:, k]):
            feet = soles[t, side:side + 2]
            gaps.append(float(feet[:, 2].min() - highest_top(feet[:, :2], clip.boxes).max()))
    gaps = np.abs(np.asarray(gaps))
    kin = compute_kinematics(motion, model)
    pelvis = kin.body_pos[:, BODY_NAMES.index("Pelvis")]
    hips = kin.body_pos[:, [BODY_NAMES.index("L_Hip"), BODY_NAMES.index("R_Hip")]].mean(axis=1)
    seated = pelvis[:, 2] < np.percentile(pelvis[:, 2], 20)
    seat_top = float(np.median(highest_top(pelvis[seated, :2], clip.boxes)))
    underside = seated_underside(motion)[seated]
    env = gym.make("CrispTrack-v0", clip=str(clip_dir))
    env.reset(seed=0)
    env.close()
    meta = json.loads((clip_dir / "meta.json").read_text())
    return {"planted_gap_median_cm": 100 * float(np.median(gaps)),
            "planted_gap_p90_cm": 100 * float(np.percentile(gaps, 90)),
            "seat_top_m": seat_top, "seated_hips_above_seat_m": float(np.median(hips[seated, 2]) - seat_top),
            "seated_pelvis_above_seat_m": float(np.median(pelvis[seated, 2]) - seat_top),
            "seated_underside_above_seat_m": float(np.median(underside) - seat_top), "loads": True,
            "static_camera": meta["quality"]["static_camera"], "registered": meta["quality"]["registered"],
            "keyframes": meta["quality"]["keyframes"], "scale_spread": meta["quality"]["scale_spread"],
            "focal_px": meta["intrinsic"][0][0], "camera_height_m": meta["quality"]["camera_height_m"],
            "implied_stature_m": meta["quality"]["implied_stature_m"],
            "scale_check": meta["quality"]["scale_check"], "floor_source": meta["quality"]["floor_source"],
            "timings": meta["timings"], "warnings": meta["quality"]["warnings"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", nargs="+", default=["folder", "mp4", "tripod"])
    parser.add_argument("--out", type=Path, default=Path("runs/bench_video"))
    args = parser.parse_args()
    if not VIDEO.is_dir():
        raise SystemExit(f"{VIDEO} is not present")
    args.out.mkdir(parents=True, exist_ok=True)
    inputs = make_inputs(args.inputs, args.out)
    rows = {}
    for name, path in inputs.items():
        start = time.perf_counter()
        clip_dir = run(ReconstructArgs(input=path, output=args.out / f"clip_{name}", fps=FPS, overwrite=True))
        rows[name] = {"wall_s": time.perf_counter() - start} | fidelity(clip_dir)
        print(json.dumps({name: rows[name]}, indent=1, default=float), flush=True)
    print("\n| input | wall (s) | person / cameras / rest (s) | camera | focal (px) | camera height (m) "
          "| scale check | planted feet above support: median / p90 (cm) | seat top (m; log 0.23-0.25) "
          "| seated hip joints / pelvis joint / underside above seat (m) | loads |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        t = r["timings"]
        rest = sum(v for k, v in t.items() if k not in ("person", "cameras"))
        camera = "fixed" if r["static_camera"] else f"SfM {r['registered']}/{r['keyframes']}"
        check = "-" if r["scale_check"] is None else f"{r['scale_check']:.2f}"
        print(f"| {name} | {r['wall_s']:.0f} | {t['person']:.0f} / {t['cameras']:.0f} / {rest:.0f} | {camera} "
              f"| {r['focal_px']:.0f} | {r['camera_height_m']:.2f} | {check} "
              f"| {r['planted_gap_median_cm']:.1f} / {r['planted_gap_p90_cm']:.1f} | {r['seat_top_m']:.3f} "
              f"| {r['seated_hips_above_seat_m']:.3f} / {r['seated_pelvis_above_seat_m']:.3f} / "
              f"{r['seated_underside_above_seat_m']:.3f} | {r['loads']} |")
    (args.out / "results.json").write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
