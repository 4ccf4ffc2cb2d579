"""The offline planner's vocabulary (the objects it knows, their words and default targets) and its checks: each
measurable requirement a constraint can hold, as the scene-API expression the program will contain
(:mod:`rewards.planner`)."""

from __future__ import annotations

from dataclasses import dataclass, field

# --------------------------------------------------------------------------------------------------------
# Vocabulary
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Entity:
    """An object word of the vocabulary: ``names`` are Scene API classes or groups for ``scene.objects``."""

    key: str
    names: tuple[str, ...]
    label: str


#: Object words (synonyms, singular; plurals are matched too) -> entity. Longer phrases win.
OBJECTS: dict[str, Entity] = {}


def _entity(key: str, names: tuple[str, ...], label: str, *phrases: str) -> None:
    ent = Entity(key, names, label)
    for phrase in phrases:
        OBJECTS[phrase] = ent


_entity("nightstand", ("nightstand",), "nightstand", "nightstand", "night stand", "night table",
        "bedside table", "bedside cabinet", "bed side table", "end table by the bed")
_entity("tv", ("tv_stand",), "TV stand", "tv stand", "tv cabinet", "tv unit", "tv console",
        "television stand", "media console", "tv", "television", "4k tv", "screen")
_entity("bed", ("bed",), "bed", "bed")
_entity("double_bed", ("double_bed",), "double bed", "double bed", "queen bed", "king bed")
_entity("single_bed", ("single_bed",), "single bed", "single bed", "twin bed")
_entity("kids_bed", ("kids_bed",), "kids bed", "kids bed", "child's bed", "children's bed", "bunk bed")
_entity("desk", ("desk",), "desk", "desk", "writing desk", "study desk", "computer desk")
_entity("chair", ("chair",), "chair", "chair", "desk chair", "office chair")
_entity("stool", ("stool",), "stool", "stool")
_entity("armchair", ("armchair",), "armchair", "armchair")
_entity("seat", ("seat",), "seat", "seat", "seating")
_entity("dressing_table", ("dressing_table",), "dressing table", "dressing table", "vanity",
        "vanity table", "makeup table")
_entity("dressing_chair", ("dressing_chair",), "dressing chair", "dressing chair", "vanity chair")
_entity("wardrobe", ("wardrobe",), "wardrobe", "wardrobe", "closet", "armoire")
_entity("cabinet", ("cabinet",), "cabinet", "cabinet", "dresser", "chest of drawers")
_entity("bookshelf", ("bookshelf",), "bookshelf", "bookshelf", "bookcase")
_entity("shelf", ("shelf",), "shelf", "shelf", "shelving")
_entity("sofa", ("sofa",), "sofa", "sofa", "couch")
_entity("coffee_table", ("coffee_table",), "coffee table", "coffee table")
_entity("dining_table", ("dining_table",), "dining table", "dining table")
_entity("dining_chair", ("dining_chair",), "dining chair", "dining chair")
_entity("table", ("table",), "table", "table")
_entity("lamp", ("lamp",), "lamp", "lamp", "light", "lighting")
_entity("support", ("support_surface",), "support surface", "support surface", "surface",
        "work surface", "tabletop")
_entity("furniture", ("ground",), "piece of furniture", "furniture", "piece of furniture", "object",
        "item", "everything")

IRREGULAR_PLURALS = {"shelf": "shelves", "bookshelf": "bookshelves", "piece of furniture": "pieces of furniture",
                      "chest of drawers": "chests of drawers", "child's bed": "children's beds",
                      "shelving": "shelving", "seating": "seating", "lighting": "lighting",
                      "furniture": "furniture", "everything": "everything"}

NUMBER_WORDS = {"zero": 0, "one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7,
                "eight": 8, "nine": 9, "ten": 10, "a pair of": 2, "a couple of": 2, "both": 2, "twin": 2}

#: Words that carry no requirement of their own (articles, copulas, room words, ...). Quantifiers (every, each, all,
#: any, some) are not filler: the rules that read them cover them (:mod:`rewards.constraint_grammar`), the words
#: no rule read are reported.
FILLER = set("""
a an the with where are is be been being so that this these those can could should must
will would of and to in on at for it its their there has have having which who whose while as by
room rooms bedroom bedrooms livingroom living diningroom dining scene scenes layout setting space home
house apartment positioned placed located arranged put position place person people someone user users
i we my our me us want need needs please make create generate design furnished also both one them they
stand stands standing kept keep do does
""".split())

#: Words understood only as context of a check kind (e.g. "robot grasping" explains a reach limit).
CONTEXT_WORDS = {
    "height": {"robot", "robotic", "grasping", "grasp", "arm", "vertical", "reach", "reachable", "limit",
               "high", "tall", "height", "above", "floor"},
    "view": {"watch", "watching", "viewer", "viewing", "sight", "comfortably", "lying"},
    "clear_path": {"move", "moving", "navigate", "navigation", "around", "access"},
}

#: Seats that count for a study zone (a desk with one of them in front).
STUDY_SEATS = ("chair", "stool", "dressing_chair")

# Default targets when the constraint names no number (metres, degrees).
VIEW_RANGE = (1.5, 3.5)        # a comfortable TV viewing distance
FARSIGHTED_MIN = 2.0           # a farsighted viewer cannot focus closer than about 2 m
UHD_MAX = 4.0                  # a 4K picture keeps its detail up to about 4 m for a bedroom-size screen
VIEW_ANGLE = 30.0              # screen within 30 degrees of the line of sight, both ways
NEAR_GAP = 0.5                 # "next to", "beside", "near"
FAR_GAP = 1.0                  # "far from", "away from"
SIDE_GAP = 0.5                 # nightstand within 0.5 m of the bed's side
FRONT_DEPTH = 0.9              # a seat up to 0.9 m in front of a desk
FRONT_MARGIN = 0.1             # ... and within the desk's width + 0.1 m laterally
WHEELCHAIR_PATH = 0.9          # clear width of wheelchair paths (ADA: 36 in)
WHEELCHAIR_TURN = 1.5          # turning circle diameter (ADA: 60 in)
TURN_NEAR = 0.5                # turning circle within 0.5 m of the bed
WALKING_PATH = 0.6             # a clear path for a walking person
WALL_GAP = 0.1                 # "against the wall": back edge within 0.1 m of the wall
ALIGN_ANGLE = 10.0             # "parallel to the walls": axes within 10 degrees of a wall's (the R_misaligned metric)

PRIMARY_WEIGHT = 2.0           # checks that carry the constraint's relation
SUPPORT_WEIGHT = 1.0           # existence and count checks the constraint asks for
IMPLIED_WEIGHT = 0.5           # existence of the objects a relation needs (partial credit)

#: Check kinds that need their objects to exist: every object such a check names (a relation's subject and
#: reference, the object a turning circle must be next to) also gets a has_<object> check of IMPLIED_WEIGHT
#: unless the constraint already counts it, so adding a missing one already pays. Not here: the checks an
#: emptier room satisfies (EMPTY_ROOM_KINDS) and the single-object requirements ("height", "wall", "aligned")
#: whose own value already includes "there is at least one".
NEEDS_OBJECTS = ("either_side", "side", "in_front", "view", "facing", "near", "turning", "away", "behind", "between")

#: Check kinds that an emptier room satisfies (no object in the way, no pair too close): reflection's
#: emphasis step leaves their weight as it is, so it can shift credit toward the checks that need objects.
EMPTY_ROOM_KINDS = ("clear_path", "far")
EMPHASIS_FACTOR = 2.0          # one emphasis step multiplies those checks' weights by this ...
EMPHASIS_CAP = 4.0             # ... up to this multiple of their original weight


# --------------------------------------------------------------------------------------------------------
# Checks and plans
# --------------------------------------------------------------------------------------------------------


@dataclass
class Param:
    """A module-level constant of the program. ``relax`` is the signed change of one curriculum step
    that makes the check easier (0: not relaxable); ``kind`` is ``threshold``, ``scale`` or ``flag``."""

    name: str
    value: float
    comment: str
    relax: float = 0.0
    kind: str = "threshold"


@dataclass
class Check:
    """One measurable check: a function body (``$NAME`` placeholders for its constants) returning a soft
    satisfaction in [0, 1] of shape (B,)."""

    key: str
    description: str
    body: str
    params: list[Param]
    weight: float = SUPPORT_WEIGHT
    phrase: str = ""
    entities: tuple[Entity, ...] = ()
    kind: str = "exists"
    curriculum: str | None = None
    """Name of the threshold a curriculum relaxes for this check (None: no curriculum)."""
    start: int = 0
    """Where its phrase starts in the constraint (checks are listed in reading order)."""
    scope: str = ""
    """How a relation is quantified (:mod:`rewards.planner_scope`): ``some``, ``every`` or ``none`` (no subject
    with the relation: an emptier room satisfies it); empty for the checks without a scope."""


@dataclass
class Plan:
    """What the planner understood: the checks, the phrases behind them, what it could not map."""

    constraint: str
    room: str
    checks: list[Check] = field(default_factory=list)
    understood: list[str] = field(default_factory=list)
    assumptions: list[str] = field(default_factory=list)
    not_understood: list[str] = field(default_factory=list)


def _objects(ent: Entity) -> str:
    return "scene.objects(" + ", ".join(repr(n) for n in ent.names) + ")"


def _frame_lines(ref_var: str) -> str:
    """Body lines giving j's offset in i's frame and i's half extents broadcast over j."""
    return f"""    offset = scene.local_offset()                       # [b, i, j]: {ref_var} i's frame
    lateral, ahead = offset[..., 0], offset[..., 1]     # + = i's left, + = in front of i
    half_w = (scene.size[..., 0] / 2).clamp(min=0.05).unsqueeze(2)
    half_d = (scene.size[..., 2] / 2).clamp(min=0.05).unsqueeze(2)
"""


def exists_check(ent: Entity, phrase: str) -> Check:
    return Check(f"has_{ent.key}", f"there is at least one {ent.label}",
                 f"    return torch.clamp(scene.count({', '.join(repr(n) for n in ent.names)}), max=1.0)\n",
                 [], SUPPORT_WEIGHT, phrase, (ent,), "exists")


def count_check(ent: Entity, lo: int, hi: int | None, phrase: str) -> Check:
    """``lo`` to ``hi`` objects (``hi`` None: no upper bound)."""
    key, names = ent.key.upper(), ", ".join(repr(n) for n in ent.names)
    params = [Param(f"{key}_MIN", float(lo), f"fewest {ent.label}s wanted")]
    if hi is None:
        desc = f"at least {lo} {ent.label}(s)"
        test = f"scene.above(n, ${key}_MIN, scale=COUNT_SCALE)"
    else:
        desc = f"exactly {lo} {ent.label}(s)" if lo == hi else f"{lo} to {hi} {ent.label}(s)"
        params.append(Param(f"{key}_MAX", float(hi), f"most {ent.label}s wanted"))
        test = f"scene.within(n, ${key}_MIN, ${key}_MAX, scale=COUNT_SCALE)"
    params.append(Param("COUNT_SCALE", 1.0, "one object off keeps exp(-1) of the credit", kind="scale"))
    return Check(f"count_{ent.key}", desc, f"    n = scene.count({names})\n    return {test}\n",
                 params, SUPPORT_WEIGHT, phrase, (ent,), "count")


def height_check(ent: Entity, limit: float, phrase: str) -> Check:
    body = f"""    mask = {_objects(ent)}
    has_any = torch.clamp(mask.float().sum(dim=1), max=1.0)
    low_enough = scene.below(scene.top_height, $HEIGHT_LIMIT, scale=$HEIGHT_SCALE)
    # "all of them": the worst one counts, plus the average so each lowered object earns credit
    return has_any * (0.5 * scene.all_of(low_enough, mask) + 0.5 * scene.mean_of(low_enough, mask))
"""
    return Check(f"height_{ent.key}", f"every {ent.label} has its top at most {limit:g} m above the floor "
                 f"(and there is at least one)", body,
                 [Param("HEIGHT_LIMIT", limit, f"m: highest allowed top of a {ent.label}", relax=0.2),
                  Param("HEIGHT_SCALE", 0.2, "m: softness of the height penalty", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (ent,), "height", "HEIGHT_LIMIT")


def either_side_check(subj: Entity, ref: Entity, phrase: str) -> Check:
    body = f"""    refs, items = {_objects(ref)}, {_objects(subj)}
    pairs = scene.pair_mask(refs, items)                # [b, i, j]: {ref.label} i, {subj.label} j
{_frame_lines(ref.label)}    # along the head half (between the headboard and the centre), 0 to SIDE_GAP out from the side
    head_half = scene.within(ahead / half_d, -1.0, 0.0, scale=$SIDE_SCALE)
    out_from_side = scene.within(lateral.abs() - half_w, 0.0, $SIDE_GAP, scale=$SIDE_SCALE)
    ok = soft_and(head_half, out_from_side)
    left = (ok * (lateral > 0)).masked_fill(~pairs, 0.0).amax(dim=2)
    right = (ok * (lateral < 0)).masked_fill(~pairs, 0.0).amax(dim=2)
    # full credit for both sides, a quarter for each side alone
    per_ref = 0.5 * left * right + 0.25 * (left + right)
    return per_ref.masked_fill(~refs, 0.0).amax(dim=1)
"""
    return Check(f"{subj.key}_either_side_of_{ref.key}",
                 f"for the best {ref.label}: a {subj.label} on its left and one on its right, each along the "
                 f"head half with its centre 0 to {SIDE_GAP:g} m out from the side", body,
                 [Param("SIDE_GAP", SIDE_GAP, f"m: {subj.label} centre at most this far out from the "
                        f"{ref.label}'s side", relax=0.25),
                  Param("SIDE_SCALE", 0.15, "softness (m, and fractions of the half depth)", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj, ref), "either_side", "SIDE_GAP")


def side_check(subj: Entity, ref: Entity, side: str, phrase: str) -> Check:
    sign = "" if side == "left" else "-"
    body = f"""    refs, items = {_objects(ref)}, {_objects(subj)}
{_frame_lines(ref.label)}    on_side = scene.below(-({sign}lateral), 0.0, scale=$SIDE_SCALE)
    close = scene.below(scene.gap(), $SIDE_NEAR, scale=$SIDE_SCALE)
    return scene.best_pair(soft_and(on_side, close), refs, items)
"""
    return Check(f"{subj.key}_{side}_of_{ref.key}",
                 f"a {subj.label} on the {side} of a {ref.label} (in its frame) within {NEAR_GAP * 2:g} m",
                 body, [Param("SIDE_NEAR", NEAR_GAP * 2, f"m: {subj.label} at most this far from the {ref.label}",
                              relax=0.5),
                        Param("SIDE_SCALE", 0.2, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj, ref), "side", "SIDE_NEAR")


def in_front_check(subj: Entity, ref: Entity, phrase: str, zone: str = "") -> Check:
    body = f"""    refs, items = {_objects(ref)}, {_objects(subj)}
{_frame_lines(ref.label)}    centred = scene.below(lateral.abs() - half_w, $FRONT_MARGIN, scale=$FRONT_SCALE)
    not_behind = scene.below(-ahead, 0.0, scale=$FRONT_SCALE)
    close = scene.below(ahead - half_d, $FRONT_DEPTH, scale=$FRONT_SCALE)
    return scene.best_pair(soft_and(centred, not_behind, close), refs, items)
"""
    what = f"{zone}: " if zone else ""
    return Check(f"{subj.key}_in_front_of_{ref.key}",
                 f"{what}a {subj.label} in front of a {ref.label} (within its width + {FRONT_MARGIN:g} m "
                 f"laterally, up to {FRONT_DEPTH:g} m beyond its front)", body,
                 [Param("FRONT_DEPTH", FRONT_DEPTH, f"m: {subj.label} at most this far beyond the front",
                        relax=0.3),
                  Param("FRONT_MARGIN", FRONT_MARGIN, "m: lateral slack beyond the half width", relax=0.15),
                  Param("FRONT_SCALE", 0.15, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj, ref), "in_front", "FRONT_DEPTH")


def view_check(target: Entity, viewer: Entity, lo: float, hi: float, angle: float, phrase: str) -> Check:
    body = f"""    viewers, targets = {_objects(viewer)}, {_objects(target)}
    angle = scene.facing_angle()                        # [b, i, j]: i's facing vs the direction i -> j
    limit = math.radians($VIEW_ANGLE_DEG)
    in_range = scene.within(scene.distance(), $VIEW_MIN, $VIEW_MAX, scale=$VIEW_DISTANCE_SCALE)
    # the {target.label} ahead of the {viewer.label}, and turned towards it
    in_sight = scene.below(angle, limit, scale=$VIEW_ANGLE_SCALE)
    turned = scene.below(angle.transpose(1, 2), limit, scale=$VIEW_ANGLE_SCALE)
    return scene.best_pair(soft_and(in_range, in_sight, turned), viewers, targets)
"""
    return Check(f"{target.key}_viewed_from_{viewer.key}",
                 f"a {viewer.label} and a {target.label} {lo:g}-{hi:g} m apart, the {target.label} within "
                 f"{angle:g} degrees of the {viewer.label}'s facing direction and facing it within {angle:g} "
                 f"degrees", body,
                 [Param("VIEW_MIN", lo, "m: closest viewing distance", relax=-0.4),
                  Param("VIEW_MAX", hi, "m: farthest viewing distance", relax=0.5),
                  Param("VIEW_ANGLE_DEG", angle, "degrees: largest viewing / facing angle", relax=15.0),
                  Param("VIEW_DISTANCE_SCALE", 0.4, "m: softness of the distance range", kind="scale"),
                  Param("VIEW_ANGLE_SCALE", 0.35, "rad: softness of the angles", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (target, viewer), "view", "VIEW_ANGLE_DEG")


def facing_check(subj: Entity, ref: Entity, angle: float, phrase: str) -> Check:
    body = f"""    items, refs = {_objects(subj)}, {_objects(ref)}
    angle = scene.facing_angle()                        # [b, i, j]: i's facing vs the direction i -> j
    return scene.best_pair(scene.below(angle, math.radians($FACING_ANGLE_DEG), scale=$FACING_SCALE), items, refs)
"""
    return Check(f"{subj.key}_facing_{ref.key}", f"a {subj.label} facing a {ref.label} within {angle:g} degrees",
                 body, [Param("FACING_ANGLE_DEG", angle, "degrees: largest facing angle", relax=15.0),
                        Param("FACING_SCALE", 0.35, "rad: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj, ref), "facing", "FACING_ANGLE_DEG")


def near_check(subj: Entity, ref: Entity, dist: float, phrase: str) -> Check:
    body = f"""    items, refs = {_objects(subj)}, {_objects(ref)}
    return scene.best_pair(scene.below(scene.gap(), $NEAR_DISTANCE, scale=$NEAR_SCALE), refs, items)
"""
    return Check(f"{subj.key}_near_{ref.key}", f"a {subj.label} within {dist:g} m of a {ref.label} "
                 f"(footprint to footprint)", body,
                 [Param("NEAR_DISTANCE", dist, "m: largest footprint gap", relax=0.3),
                  Param("NEAR_SCALE", 0.2, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj, ref), "near", "NEAR_DISTANCE")


def far_check(subj: Entity, ref: Entity, dist: float, phrase: str) -> Check:
    body = f"""    pairs = scene.pair_mask({_objects(ref)}, {_objects(subj)})
    apart = scene.above(scene.gap(), $FAR_DISTANCE, scale=$FAR_SCALE)
    # every pair must keep the distance: the closest pair counts
    return apart.masked_fill(~pairs, 1.0).amin(dim=2).amin(dim=1)
"""
    return Check(f"{subj.key}_away_from_{ref.key}", f"every {subj.label} at least {dist:g} m from every "
                 f"{ref.label} (footprint to footprint)", body,
                 [Param("FAR_DISTANCE", dist, "m: smallest footprint gap", relax=-0.3),
                  Param("FAR_SCALE", 0.2, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj, ref), "far", "FAR_DISTANCE")


def wall_check(subj: Entity, phrase: str) -> Check:
    body = f"""    mask = {_objects(subj)}
    has_any = torch.clamp(mask.float().sum(dim=1), max=1.0)
    backed = scene.below(scene.back_to_wall(), $WALL_GAP, scale=$WALL_SCALE)
    return has_any * scene.all_of(backed, mask)
"""
    return Check(f"{subj.key}_against_wall", f"every {subj.label} with its back within {WALL_GAP:g} m of a wall",
                 body, [Param("WALL_GAP", WALL_GAP, "m: largest gap between the back and the wall", relax=0.2),
                        Param("WALL_SCALE", 0.15, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj,), "wall", "WALL_GAP")


def aligned_check(subj: Entity, phrase: str) -> Check:
    body = f"""    mask = {_objects(subj)}
    has_any = torch.clamp(mask.float().sum(dim=1), max=1.0)
    square = scene.below(scene.wall_angle(), math.radians($ALIGN_ANGLE_DEG), scale=$ALIGN_SCALE)
    return has_any * scene.all_of(square, mask)
"""
    return Check(f"{subj.key}_aligned_with_walls", f"every {subj.label} within {ALIGN_ANGLE:g} degrees of parallel "
                 f"to a wall", body,
                 [Param("ALIGN_ANGLE_DEG", ALIGN_ANGLE, "degrees: largest angle to the nearest wall direction",
                        relax=10.0),
                  Param("ALIGN_SCALE", 0.1, "rad: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj,), "aligned", "ALIGN_ANGLE_DEG")


def clear_path_check(width: float, phrase: str) -> Check:
    body = """    ground = scene.objects("ground")
    radius = $PATH_WIDTH / 2
    # 1 for a reached object, less the narrower its path (a gradient that opens the path)
    reach = scene.above(scene.path_clearance(radius=radius), radius, scale=$PATH_SCALE)
    # the fraction of reachable objects is the partial credit; all of them is full credit
    score = 0.5 * scene.mean_of(reach, ground) + 0.5 * scene.all_of(reach, ground)
    if PARTIAL_CREDIT:
        narrower = scene.reachable(radius=radius * PARTIAL_SHRINK).float()
        score = 0.8 * score + 0.2 * scene.mean_of(narrower, ground)
    return score
"""
    return Check("clear_paths", f"paths at least {width:g} m wide (agent radius {width / 2:g} m) reach every "
                 f"ground object", body,
                 [Param("PATH_WIDTH", width, "m: clear width of the paths", relax=-0.15),
                  Param("PATH_SCALE", 0.1, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (), "clear_path", "PATH_WIDTH")


def turning_check(diameter: float, near: Entity | None, phrase: str) -> Check:
    near_arg = _objects(near) if near else "None"
    where = f"within {TURN_NEAR:g} m of a {near.label}" if near else "anywhere on the free floor"
    body = f"""    near = {near_arg}
    radius = $TURN_DIAMETER / 2
    # 1 when the circle fits, less the smaller the largest free circle there (a gradient that makes room)
    full = scene.above(scene.circle_clearance(radius, near=near, within=$TURN_NEAR), radius, scale=$TURN_SCALE)
    if not PARTIAL_CREDIT:
        return full
    # partial credit: a smaller circle at the same place, or the full circle anywhere
    smaller = scene.free_circle(radius * PARTIAL_SHRINK, near=near, within=$TURN_NEAR).float()
    anywhere = scene.free_circle(radius).float()
    return 0.6 * full + 0.2 * smaller + 0.2 * anywhere
"""
    return Check("turning_circle", f"a free turning circle of {diameter:g} m diameter {where}", body,
                 [Param("TURN_DIAMETER", diameter, "m: diameter of the free circle", relax=-0.25),
                  Param("TURN_NEAR", TURN_NEAR, "m: largest gap between the circle and the object", relax=0.5),
                  Param("TURN_SCALE", 0.1, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (near,) if near else (), "turning", "TURN_DIAMETER")
