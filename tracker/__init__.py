"""Stage 1 of the video path: landmark schemes, label/track formats, video I/O and the
person-specific eigen-points tracker (004_119ba07521a9af0b.txt, section 3)."""
