"""Static files of the pose-correction page and the landmark-correction page (landmarks.html, landmarks.js;
the style is shared): a package so that they install as package data."""
