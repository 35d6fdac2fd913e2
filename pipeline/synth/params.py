"""The numbers that shape a synthetic plot: classes, sizes, CRS, scanner model, scene content."""

from dataclasses import dataclass

#: LAS classification code of each class (dead wood uses a user-definable code >= 64).
SYNTH_CLASSES: dict[str, int] = {"terrain": 2, "tree": 5, "dead_wood": 64, "misc": 1}

DEFAULT_SIZE = 30.0  # metres: about 200,000 points
DEFAULT_TILE_SIZE = 15.0  # metres: the default plot spans 2 x 2 tiles
DEFAULT_ORIGIN = (500000.0, 5500000.0, 400.0)  # lower-left corner of the plot, ground level
MIN_SIZE = 5.0  # metres: smaller plots cannot hold one object of every class
MAX_SIZE = 300.0  # metres: about 23 million points; writing them peaks at about 0.6 GiB

#: ETRS89 / UTM zone 32N (EPSG:25832) as OGC WKT, written into every tile.
CRS_WKT = (
    'PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_'
    'System_1989",SPHEROID["GRS 1980",6378137,298.257222101,AUTHORITY["EPSG","7019"]],'
    'TOWGS84[0,0,0,0,0,0,0],AUTHORITY["EPSG","6258"]],PRIMEM["Greenwich",0,AUTHORITY["EPSG",'
    '"8901"]],UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]],AUTHORITY["EPSG",'
    '"4258"]],PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],'
    'PARAMETER["central_meridian",9],PARAMETER["scale_factor",0.9996],PARAMETER["false_'
    'easting",500000],PARAMETER["false_northing",0],UNIT["metre",1,AUTHORITY["EPSG","9001"]],'
    'AXIS["Easting",EAST],AXIS["Northing",NORTH],AUTHORITY["EPSG","25832"]]'
)

# --- scanner model -------------------------------------------------------------------------
BASE_DENSITY = 180.0  # surface samples per m^2 before thinning: the density cap near a scanner
FULL_DENSITY_RANGE = 4.0  # metres: closer than this a scanner keeps every sample
NEAREST_SCANNERS = 4  # scans merged into the density of a point (the nearest ones)
SCANNER_HEIGHT = 1.5  # metres above the ground
SCANNER_SPACING = 15.0  # metres: one scan position per SCANNER_SPACING^2 of plot, at least 3
RANGE_NOISE = (0.002, 0.0003)  # sigma = a + b * range (metres): ~5 mm at 10 m, ~11 mm at 30 m
OCCLUSION_TOLERANCE = 0.02  # metres: a stem closer than this to its own sample does not hide it

# --- scene content (per m^2 of plot) ---------------------------------------------------------
TREE_DENSITY = 0.022  # stems per m^2 (220 per hectare)
TREE_MARGIN = 4.0  # metres around the plot where trees still grow (their crowns reach in)
LOG_DENSITY = 0.01
FALLEN_BRANCH_DENSITY = 0.008
SNAG_DENSITY = 0.003
SHRUB_DENSITY = 0.018
ROCK_DENSITY = 0.006
FOLIAGE_AREA = 0.8  # foliage samples per m^2 of crown envelope, relative to BASE_DENSITY
SHRUB_AREA = 1.2  # the same for shrubs
BATCH = 1 << 20  # candidate samples scanned at once (bounds temporary memory)


@dataclass(frozen=True)
class Stand:
    """What makes a synthetic stand closer to a real one; the default is the plain plot (the
    same points, bit for bit, as without it).

    touching : share (0-1) of the trees set beside an earlier tree so that their crowns touch
        and interlock (stems 75-95 % of the sum of the two crown radii apart).
    suppressed : suppressed trees per dominant tree (0-1): small trees standing under a
        dominant tree's crown, their top 45-85 % of its crown base.
    lean : degrees (0-15): every stem leans by between half this and this, in a random
        direction (0: the plain plot's slight lean, 1-2 degrees).
    slope : degrees (0-60): the stand grows on a hillside this steep, in a random direction
        (0: the plain plot's gentle 3-18 % grade); the plot's other draws are unchanged.
    ridge : the ground is a ridge along the middle of the plot, its two faces falling at
        the slope (``slope``, or the plain grade) on either side.
    """

    touching: float = 0.0
    suppressed: float = 0.0
    lean: float = 0.0
    slope: float = 0.0
    ridge: bool = False


#: A stand with every kind of realism switched on (``silva synth``'s plain plot is Stand()).
REAL_STAND = Stand(touching=0.5, suppressed=0.3, lean=5.0)
MAX_LEAN = 15.0  # degrees
MAX_SLOPE = 60.0  # degrees
