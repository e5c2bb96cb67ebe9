"""Synthetic data with exact ground truth, upstream of reconstruction: box scenes with a
procedurally generated, kinematically consistent motion (the bundled clips), and depth videos of
them with the errors of a monocular depth network (the reconstruction benchmarks).

Clips (``crisp synth-clips``): :mod:`~crisp_gym.synth.scenes` (stairs, platform, seat),
:mod:`~crisp_gym.synth.skeleton` (the humanoid's leg geometry), :mod:`~crisp_gym.synth.gait` (the
walk plan, balanced as an inverted pendulum), :mod:`~crisp_gym.synth.swing` (swing arcs that clear
every edge), :mod:`~crisp_gym.synth.ik` (joint angles), :mod:`~crisp_gym.synth.sitting` and
:mod:`~crisp_gym.synth.clips` (:func:`~crisp_gym.synth.clips.make_clip`, the bundled set).

Videos (``crisp synth``): :mod:`~crisp_gym.synth.camera`, :mod:`~crisp_gym.synth.depth_noise`,
:mod:`~crisp_gym.synth.video` (rendering), :mod:`~crisp_gym.synth.truth` (files and ground truth)
and :mod:`~crisp_gym.synth.video_cli`.

The generator plans in a path frame: arc length ``s`` along a planar path and a lateral offset. The
motion is assembled in stages:

1. a footstep plan (which foot lands where and when; anchors on treads and platform edges,
   filled with even steps on level ground) and pelvis keyframes per channel (progress, sway,
   height, lean), interpolated with shape-preserving cubic splines so nothing overshoots; while
   walking, progress and sway are those of a linear inverted pendulum whose centre of pressure
   follows the feet, so that a body can balance on the motion (:mod:`crisp_gym.balance`);
2. swing arcs whose lift height is the smallest that keeps the foot clear of all boxes;
3. the pelvis height limited by what the legs can reach, with small vertical accelerations;
4. leg IK (hip's three hinges, knee flexion, ankle keeping the foot flat), counter-swinging arms,
   trunk lean, a level head; then a check with MuJoCo forward kinematics that lowers the pelvis
   where a stance foot does not reach its surface.

Because the ground truth is exact, these clips measure the rest of the project (reconstruction,
contact detection, tracking) without the noise of a video. This package imports reconstruction's
input format and ray caster (it writes what reconstruction reads); reconstruction never imports it.
"""
