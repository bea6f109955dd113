"""Stage 2 of the video path: key-shape selection and non-negative weights
(004_119ba07521a9af0b.txt, section 4)."""
