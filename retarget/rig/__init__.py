"""An artist's blendshape rig: loaded, its landmarks, its curves solved from a take, the pose library."""
