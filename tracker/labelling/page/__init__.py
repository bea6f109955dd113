"""Static files of the label-correction page (a package so that they install as package data)."""
