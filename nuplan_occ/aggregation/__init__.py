"""Foreground-background separate aggregation: a sweep split by its boxes (split), background gathered in
the scene frame and objects in their box frames (aggregate), moving unboxed points told apart (dynamic),
solids carved by rays (carve), ground holes filled (ground_fill) and boxes culled (box_cull). Pure
functions, no file I/O."""
