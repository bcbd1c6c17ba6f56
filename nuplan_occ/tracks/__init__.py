"""Box refinement of tracked objects: each track's boxes registered against the track's own points
(track_refine, with the 4-DoF ICP of track_icp) and static small objects snapped onto their points
(box_snap). Pure functions, no file I/O."""
