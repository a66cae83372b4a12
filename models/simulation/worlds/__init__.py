"""Worlds from real scans: any scanned scene as simulation mode's ground truth (issue 34).

A *world* is a scan (textured or coloured mesh, point cloud, posed RGB-D sequence) loaded into the simulation's
ground-truth frame (metres, z up, floor at z = 0): ``load.load_world`` reads it, ``scene.ScanScene`` renders it
with Open3D's ``RaycastingScene`` (colour from the texture at the hit's barycentric UV), ``views.start_views``
chooses input cameras in its free space, ``patches`` builds the per-clip hallucinated variants and ``demo``
writes a demo collection from it (``navcrafter demo-data OUT --world FILE``).

Scans are incomplete: a ray that hits nothing is *no data* (``NO_DATA_RGB`` in colour, depth 0, ``hit`` False),
never free space: the conservative occupancy of ``scene.ScanRaycaster`` counts unscanned space as an obstacle.
"""

NO_DATA_RGB = (255, 0, 255)  # colour of a pixel whose ray hits no scanned surface (explicit, never texture)
SCAN_KIND = "scan"  # scene spec "kind" of a world (the generated scenes use room / street / tabletop)
WORLD_VERSION = 1  # bump when the stored world format or its rendering changes
WORLDS_DIR = "worlds"  # <photos>/.groundtruth/worlds/<world name>/world.npz: one copy per world

LABEL = ("SIMULATION MODE: rendered from a real scan used as ground truth (holes render as 'no data' magenta), "
         "not produced by learned models")


class WorldError(ValueError):
    """A scan cannot be used as a world; the message names the file and the fix."""
