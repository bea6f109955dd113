"""Static files of the pose-correction page (a package so that they install as package data)."""
