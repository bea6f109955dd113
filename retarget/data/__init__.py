"""Data shipped with keyshape.retarget: the ICT-FaceKit face subset (see LICENSE-ICT-FaceKit.txt)."""
