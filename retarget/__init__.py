"""Stage 3: weights onto the artist's key shapes (004_119ba07521a9af0b.txt, section 5), and
the 3D marker path in :mod:`keyshape.retarget.mocap` (001_7296bf6ea73cabea.txt, 002_dce09d5f5656b088.txt)."""
