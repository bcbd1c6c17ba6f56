"""Import of the paper's released Nuplan-Occ into our dataset format (`nuplan-occ import-release`).

`files` reads one release file, `label_maps` maps its ids to ours, `regrid` moves its grid onto ours,
`logs` finds a token's metadata in the nuPlan DBs, `importer` streams a release folder into shards,
`compare` draws one frame of two datasets side by side.
"""

from nuplan_occ.release.errors import ReleaseImportError

__all__ = ["ReleaseImportError"]
