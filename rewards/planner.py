"""The offline reward planner: the reward-synthesis agent when no language model is configured.

It reads a constraint the way the agent would, but with a small, readable vocabulary instead of a model:

* **objects** ("night tables", "bedside table", "TV", "desk", "support surfaces", ...) map onto the
  Scene API's classes and groups (:data:`OBJECTS`);
* **quantities** ("1.0 m", "90 cm", "30 degrees", "2 night tables", "two chairs", "at least 3 ...");
* **relations and requirements** ("on either side of", "left/right of", "in front of", "facing",
  "view ... from", "within a 1.0 m reach", "against the wall", "parallel to the walls", "within 1 m of",
  "wheelchair-accessible", "turning circle", "clear path", "study zone", "farsighted" / "4K" for viewing
  distances, ...).

Each recognised phrase becomes a :class:`Check`: a description, the body of a small function written
against :mod:`rewards.scene_api` only, and its thresholds as named module-level UPPER_CASE constants.
Every check returns a *soft* satisfaction in [0, 1] (1 when it holds, decaying smoothly with the
distance to holding), so the reward gives partial credit that RL can climb. The program is the weighted
mean of the checks. Words it cannot map are reported in ``not_understood`` and in the reasoning, never
guessed; a constraint with nothing understood raises :class:`ValueError`.

:meth:`OfflinePlanner.reflect` reads the task success trend: a statistically failing reward gets a
curriculum (the main threshold relaxed, then tightened stage by stage), then a simplification (softer,
denser terms), then an emphasis (more weight on the checks that need the constraint's objects, up to a
cap); a rising one is kept; a high one tightens the curriculum toward the target; sandbox failures (NaN,
errors, timeouts) give a safer program. Reflection never drops a check: every check measures part of the
constraint, and a reward without one would stop measuring it (the policy then climbs the reward while the
constraint fails). Everything is deterministic.
"""

from __future__ import annotations

import ast
import math
import re
import textwrap
from dataclasses import dataclass, field
from string import Template

from .proposal import ReflectionContext, RewardProposal

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

_IRREGULAR_PLURALS = {"shelf": "shelves", "bookshelf": "bookshelves", "piece of furniture": "pieces of furniture",
                      "chest of drawers": "chests of drawers", "child's bed": "children's beds",
                      "shelving": "shelving", "seating": "seating", "lighting": "lighting",
                      "furniture": "furniture", "everything": "everything"}

NUMBER_WORDS = {"zero": 0, "one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7,
                "eight": 8, "nine": 9, "ten": 10, "a pair of": 2, "a couple of": 2, "both": 2, "twin": 2}

#: Words that carry no requirement of their own (articles, copulas, room words, ...).
FILLER = set("""
a an the with where all every each any are is be been being so that this these those can could should must
will would of and to in on at for it its their there has have having which who whose while as by some
room rooms bedroom bedrooms livingroom living diningroom dining scene scenes layout setting space home
house apartment positioned placed located arranged put position place person people someone user users
i we my our me us want need needs please make create generate design furnished also both one them they
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
NEEDS_OBJECTS = ("either_side", "side", "in_front", "view", "facing", "near", "turning")

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
    reach = scene.reachable(radius=$PATH_WIDTH / 2).float()
    # the fraction of reachable objects is the partial credit; all of them is full credit
    score = 0.5 * scene.mean_of(reach, ground) + 0.5 * scene.all_of(reach, ground)
    if PARTIAL_CREDIT:
        narrower = scene.reachable(radius=$PATH_WIDTH / 2 * PARTIAL_SHRINK).float()
        score = 0.8 * score + 0.2 * scene.mean_of(narrower, ground)
    return score
"""
    return Check("clear_paths", f"paths at least {width:g} m wide (agent radius {width / 2:g} m) reach every "
                 f"ground object", body,
                 [Param("PATH_WIDTH", width, "m: clear width of the paths", relax=-0.15)],
                 PRIMARY_WEIGHT, phrase, (), "clear_path", "PATH_WIDTH")


def turning_check(diameter: float, near: Entity | None, phrase: str) -> Check:
    near_arg = _objects(near) if near else "None"
    where = f"within {TURN_NEAR:g} m of a {near.label}" if near else "anywhere on the free floor"
    body = f"""    near = {near_arg}
    full = scene.free_circle($TURN_DIAMETER / 2, near=near, within=$TURN_NEAR).float()
    if not PARTIAL_CREDIT:
        return full
    # partial credit: a smaller circle at the same place, or the full circle anywhere
    smaller = scene.free_circle($TURN_DIAMETER / 2 * PARTIAL_SHRINK, near=near, within=$TURN_NEAR).float()
    anywhere = scene.free_circle($TURN_DIAMETER / 2).float()
    return 0.6 * full + 0.2 * smaller + 0.2 * anywhere
"""
    return Check("turning_circle", f"a free turning circle of {diameter:g} m diameter {where}", body,
                 [Param("TURN_DIAMETER", diameter, "m: diameter of the free circle", relax=-0.25),
                  Param("TURN_NEAR", TURN_NEAR, "m: largest gap between the circle and the object", relax=0.5)],
                 PRIMARY_WEIGHT, phrase, (near,) if near else (), "turning", "TURN_DIAMETER")


# --------------------------------------------------------------------------------------------------------
# Reading the constraint
# --------------------------------------------------------------------------------------------------------

_NUM = r"\d+(?:\.\d+)?"
_UNIT = r"(?:m|cm|mm|meters?|metres?|centimeters?|centimetres?|millimeters?|millimetres?|ft|feet|foot|degrees?|deg)"
QTY = rf"(?:{_NUM}) ?{_UNIT}\b"
_TO_METRES = {"cm": 0.01, "centimeter": 0.01, "centimetre": 0.01, "mm": 0.001, "millimeter": 0.001,
              "millimetre": 0.001, "ft": 0.3048, "feet": 0.3048, "foot": 0.3048}


def quantity(text: str) -> float:
    """The value of a quantity like ``90 cm`` in metres (degrees stay degrees)."""
    m = re.match(rf"({_NUM}) ?([a-z]+)", text.strip())
    value, unit = float(m.group(1)), m.group(2)
    return value * _TO_METRES.get(unit if unit == "feet" else unit.rstrip("s"), 1.0)


@dataclass
class _Mention:
    start: int
    end: int
    entity: Entity
    used: bool = False


class _Reader:
    """Finds object mentions, quantities and relation phrases in a normalised constraint."""

    def __init__(self, constraint: str, room: str):
        self.plan = Plan(constraint, room)
        self.text = self.normalise(constraint)
        self.words = [(m.start(), m.end(), m.group()) for m in re.finditer(r"[a-z0-9.']+", self.text)]
        self.covered = [False] * len(self.words)
        self.mentions = self.find_mentions()

    @staticmethod
    def normalise(text: str) -> str:
        t = text.lower().replace("’", "'")
        t = re.sub(r"[-_/]", " ", t)
        t = re.sub(r"(?<!\d)\.|\.(?!\d)", " ", t)                 # periods that are not decimal points
        t = re.sub(r"[^a-z0-9.'\s]", " ", t)
        for word, value in sorted(NUMBER_WORDS.items(), key=lambda kv: -len(kv[0])):
            if word in ("twin", "both"):
                continue
            t = re.sub(rf"\b{word}\b", str(value), t)
        return re.sub(r"\s+", " ", t).strip()

    # -- bookkeeping ----------------------------------------------------------------------------------
    def cover(self, start: int, end: int) -> None:
        for k, (s, e, _) in enumerate(self.words):
            if s >= start and e <= end:
                self.covered[k] = True

    def find_mentions(self) -> list[_Mention]:
        found: list[_Mention] = []
        phrases = sorted(OBJECTS, key=lambda p: (-len(p), p))
        for phrase in phrases:
            plural = _IRREGULAR_PLURALS.get(phrase, phrase + "s")
            pattern = rf"\b(?:{re.escape(plural)}|{re.escape(phrase)}(?:es)?)\b"
            for m in re.finditer(pattern, self.text):
                if not any(m.start() < f.end and f.start < m.end() for f in found):
                    found.append(_Mention(m.start(), m.end(), OBJECTS[phrase]))
        return sorted(found, key=lambda f: f.start)

    def before(self, pos: int, exclude: Entity | None = None) -> _Mention | None:
        cands = [m for m in self.mentions if m.end <= pos and m.entity != exclude]
        return cands[-1] if cands else None

    def after(self, pos: int, limit: int | None = None) -> _Mention | None:
        cands = [m for m in self.mentions if m.start >= pos and (limit is None or m.start < limit)]
        return cands[0] if cands else None

    def reference_after(self, pos: int, subject: _Mention | None) -> _Mention | None:
        """The object named after a relation; ``it``/``them`` refer back to the object before the subject."""
        rest = self.text[pos:].lstrip()
        if re.match(r"(?:it|them)\b", rest) and subject is not None:
            self.cover(pos, pos + len(self.text[pos:]) - len(rest) + 4)
            return self.before(subject.start, exclude=subject.entity)
        return self.after(pos)

    def add(self, check: Check, start: int, end: int, *mentions: _Mention | None, meaning: str = "") -> None:
        for m in mentions:
            if m is not None:
                m.used = True
                self.cover(m.start, m.end)
        self.cover(start, end)
        phrase = self.text[start:end]
        if not check.phrase:
            check.phrase = phrase
        existing = [c for c in self.plan.checks if c.key == check.key]
        if existing:            # the same requirement said twice: keep the first
            return
        check.start = start
        self.plan.checks.append(check)
        self.plan.understood.append(f"'{check.phrase}' -> {meaning or check.description}")

    def has_kind(self, kind: str) -> bool:
        return any(c.kind == kind for c in self.plan.checks)


def _rule_zones(r: _Reader) -> None:
    for m in re.finditer(r"\b(?:functional |dedicated |proper )?(?:study|work|working|office|homework|reading and "
                         r"writing) (?:zone|area|corner|space|nook|station|spot)\b|\b(?:functional )?workspace\b|"
                         r"\bhome office\b|\bworkstation\b", r.text):
        desk = OBJECTS["desk"]
        seat = Entity("study_seat", STUDY_SEATS, "chair, stool or dressing chair")
        r.add(in_front_check(seat, desk, m.group(), zone="study zone"), m.start(), m.end(),
              meaning="a study zone = a desk with a chair, stool or dressing chair in front of it")
    for m in re.finditer(r"\b(?:dressing|vanity|makeup) (?:zone|area|corner|station|spot)\b", r.text):
        seat = Entity("vanity_seat", ("dressing_chair", "stool", "chair"), "dressing chair, stool or chair")
        r.add(in_front_check(seat, OBJECTS["dressing table"], m.group(), zone="dressing zone"), m.start(), m.end(),
              meaning="a dressing zone = a dressing table with a seat in front of it")


def _rule_wheelchair(r: _Reader) -> None:
    for m in re.finditer(r"\bwheelchair(?: (?:accessible|friendly|users?|user's|access|bound|accessibility))?\b|"
                         r"\bbarrier free\b|\baccessible\b", r.text):
        near = OBJECTS["bed"] if r.plan.room == "bedroom" else OBJECTS["sofa"] if "living" in r.plan.room else None
        r.add(clear_path_check(WHEELCHAIR_PATH, m.group()), m.start(), m.end(),
              meaning=f"wheelchair access: {WHEELCHAIR_PATH:g} m clear paths to every object")
        r.add(turning_check(WHEELCHAIR_TURN, near, m.group()), m.start(), m.end(),
              meaning=f"wheelchair access: a {WHEELCHAIR_TURN:g} m turning circle"
                      + (f" next to the {near.label}" if near else ""))


def _rule_turning(r: _Reader) -> None:
    for m in re.finditer(rf"\b(?:(?P<q1>{QTY}) (?:wide |diameter )?)?turning (?:circle|space|area|radius)"
                         rf"(?: (?:of )?(?:at least )?(?P<q2>{QTY}))?", r.text):
        q = m.group("q1") or m.group("q2")
        diameter = quantity(q) * (2 if "radius" in m.group() else 1) if q else WHEELCHAIR_TURN
        r.plan.checks = [c for c in r.plan.checks if c.kind != "turning"]
        subject = r.after(m.end())
        link = subject and re.search(r"\b(?:near|next to|beside|by)\b", r.text[m.end():subject.start])
        near = subject.entity if link else None
        if link:                # "near the sofa" is read here, not again as a distance relation
            r.cover(m.end() + link.start(), m.end() + link.end())
        if near is None and r.plan.room == "bedroom" and r.has_kind("clear_path"):
            near = OBJECTS["bed"]
        r.add(turning_check(diameter, near, m.group()), m.start(), m.end(), subject if near else None)


def _rule_paths(r: _Reader) -> None:
    paths = r"(?:paths?|passages?|walkways?|aisles?|circulation)"
    for m in re.finditer(rf"\b(?:(?P<q1>{QTY}) (?:wide )?(?:clear |free |open )?{paths}|"
                         rf"(?:clear|free|open|unobstructed|wide) {paths}(?: (?:of )?(?:at least )?"
                         rf"(?P<q2>{QTY})(?: wide)?)?)", r.text):
        q = m.group("q1") or m.group("q2")
        width = quantity(q) if q else WALKING_PATH
        r.plan.checks = [c for c in r.plan.checks if c.kind != "clear_path"]
        r.add(clear_path_check(width, m.group()), m.start(), m.end())


def _rule_view(r: _Reader) -> None:
    verbs = r"\b(?:view|views|viewed|viewing|watch|watches|watched|watching|see|sees|seen|visible)\b"
    for m in re.finditer(verbs, r.text):
        frm = re.compile(r"\bfrom\b").search(r.text, m.end())
        if not frm:
            continue
        target = r.after(m.end(), limit=frm.start()) or r.before(m.start())
        viewer = r.after(frm.end())
        if target is None or viewer is None:
            continue
        lo, hi = VIEW_RANGE
        notes = []
        far = re.search(r"\b(?:farsighted|far sighted|long sighted|longsighted|hyperopic|presbyopic)\b", r.text)
        if far:
            lo = FARSIGHTED_MIN
            r.cover(far.start(), far.end())
            notes.append(f"'{far.group()}' -> no closer than {FARSIGHTED_MIN:g} m (a farsighted viewer cannot "
                         f"focus on a near screen)")
        uhd = re.search(r"\b(?:4k|uhd|ultra hd|2160p)\b", r.text)
        if uhd:
            hi = UHD_MAX
            r.cover(uhd.start(), uhd.end())
            notes.append(f"'{uhd.group()}' -> up to {UHD_MAX:g} m (a 4K picture keeps its detail to about "
                         f"{UHD_MAX:g} m for a bedroom-size screen)")
        rng = re.search(rf"\bbetween (?P<lo>{_NUM}) ?(?P<unit>{_UNIT})? and (?P<hi>{QTY})", r.text)
        if rng:
            unit = rng.group("unit") or re.sub(_NUM, "", rng.group("hi")).strip()
            lo, hi = quantity(f"{rng.group('lo')} {unit}"), quantity(rng.group("hi"))
            r.cover(rng.start(), rng.end())
            notes.append(f"'{rng.group()}' -> viewing distance {lo:g} to {hi:g} m")
        r.add(view_check(target.entity, viewer.entity, lo, hi, VIEW_ANGLE, r.text[m.start():frm.end()]),
              m.start(), frm.end(), target, viewer)
        r.plan.understood.extend(notes)
        if target.entity.key == "tv":
            r.plan.assumptions.append("The scene has no separate TV class: the TV stands on the TV stand, so the "
                                      "stand's position and facing stand for the screen's.")


def _rule_height(r: _Reader) -> None:
    patterns = [rf"\bwithin (?:a |an |the )?(?P<q>{QTY}) (?:vertical )?(?:reach|height)(?: limit)?",
                rf"\b(?:at most|no (?:higher|taller) than|not (?:higher|taller) than|below|under|lower than|"
                rf"shorter than|max(?:imum)?(?: height)?(?: of)?) (?P<q>{QTY})(?! (?:away|from|of)\b)"
                rf"(?: (?:high|tall|above the floor|in height))?"]
    for pattern in patterns:
        for m in re.finditer(pattern, r.text):
            if "deg" in m.group("q"):
                continue
            subject = r.before(m.start())
            if subject is None:
                r.plan.not_understood.append(f"{m.group()} (no object named before it)")
                r.cover(m.start(), m.end())
                continue
            r.add(height_check(subject.entity, quantity(m.group("q")), m.group()), m.start(), m.end(), subject)


def _rule_distance(r: _Reader) -> None:
    near_q = rf"\b(?:within|at most|no more than|less than|no farther than) (?P<q>{QTY}) (?:away )?(?:of|from)\b"
    far_q = (rf"\b(?:at least|no less than|more than|minimum of) (?P<q>{QTY}) (?:away )?from\b|"
             rf"\b(?P<q2>{QTY}) (?:or more )?away from\b")
    near_w = r"\b(?:next to|beside|near|close to|adjacent to|alongside)\b"
    for pattern, kind in ((near_q, "near"), (far_q, "far"), (near_w, "near_word")):
        for m in re.finditer(pattern, r.text):
            if any(r.covered[k] for k, (s, e, _) in enumerate(r.words) if s >= m.start() and e <= m.end()):
                continue
            subject, ref = r.before(m.start()), None
            ref = r.reference_after(m.end(), subject)
            if subject is None or ref is None:
                r.plan.not_understood.append(f"'{m.group()}' (needs an object before and after it)")
                r.cover(m.start(), m.end())
                continue
            if kind == "far":
                check = far_check(subject.entity, ref.entity, quantity(m.group("q") or m.group("q2")), m.group())
            else:
                dist = quantity(m.group("q")) if kind == "near" else NEAR_GAP
                check = near_check(subject.entity, ref.entity, dist, m.group())
            r.add(check, m.start(), m.end(), subject, ref)


def _rule_relations(r: _Reader) -> None:
    rules = [
        (r"\b(?:on |at )?(?:either|both|each|opposite) sides? of\b|\bflank(?:ing|ed|s)?\b|\bon each side of\b",
         "either_side"),
        (r"\b(?:on |to )?(?:the )?left(?: hand)?(?: side)? of\b", "left"),
        (r"\b(?:on |to )?(?:the )?right(?: hand)?(?: side)? of\b", "right"),
        (r"\bin front of\b", "in_front"),
        (r"\bfac(?:ing|es|e)(?: towards?| to)?\b", "facing"),
        (r"\b(?:against|along|touching|flush with|backed (?:up )?against) (?:the |a |one )?walls?\b", "wall"),
        (r"\b(?:parallel (?:to|with)|aligned (?:to|with)|square (?:to|with)|straight (?:to|with)) (?:the |a |its )?"
         r"walls?\b", "aligned"),
    ]
    for pattern, kind in rules:
        for m in re.finditer(pattern, r.text):
            subject = r.before(m.start())
            if kind in ("wall", "aligned"):
                if subject is None:
                    r.plan.not_understood.append(f"'{m.group()}' (no object named before it)")
                    r.cover(m.start(), m.end())
                    continue
                check = wall_check if kind == "wall" else aligned_check
                r.add(check(subject.entity, m.group()), m.start(), m.end(), subject)
                continue
            ref = r.reference_after(m.end(), subject)
            if subject is None or ref is None:
                r.plan.not_understood.append(f"'{m.group()}' (needs an object before and after it)")
                r.cover(m.start(), m.end())
                continue
            s, o = subject.entity, ref.entity
            if kind == "either_side":
                check = either_side_check(s, o, m.group())
            elif kind in ("left", "right"):
                check = side_check(s, o, kind, m.group())
            elif kind == "in_front":
                check = in_front_check(s, o, m.group())
            else:
                angle = re.compile(rf"\bwithin (?P<q>{_NUM}) ?deg(?:rees?)?\b").match(r.text, ref.end + 1)
                if angle:
                    r.cover(angle.start(), angle.end())
                check = facing_check(s, o, float(angle.group("q")) if angle else VIEW_ANGLE, m.group())
            r.add(check, m.start(), m.end(), subject, ref)


def _rule_counts(r: _Reader) -> None:
    quals = {"at least": "min", "no fewer than": "min", "no less than": "min", "more than": "more",
             "at most": "max", "no more than": "max", "up to": "max", "fewer than": "less", "less than": "less",
             "exactly": "exact", "only": "exact"}
    qual_re = "|".join(sorted(quals, key=len, reverse=True))
    for m in re.finditer(rf"\b(?:(?P<qual>{qual_re}) )?(?P<n>\d+) (?=[a-z])", r.text):
        obj = r.after(m.end())
        if obj is None or obj.start != m.end():
            continue
        n, mode = int(m.group("n")), quals.get(m.group("qual") or "", "plain")
        lo, hi = {"min": (n, None), "more": (n + 1, None), "max": (0, n), "less": (0, max(n - 1, 0)),
                  "exact": (n, n), "plain": (n, None)}[mode]
        if mode == "plain":
            r.plan.assumptions.append(f"'{m.group('n')} {r.text[obj.start:obj.end]}' read as at least {n} "
                                      f"(an extra one elsewhere does not break the request).")
        r.add(count_check(obj.entity, lo, hi, r.text[m.start():obj.end]), m.start(), obj.end, obj)
    for m in re.finditer(r"\b(?:no|without(?: (?:a|an|any))?)\b (?=[a-z])", r.text):
        obj = r.after(m.end())
        if obj is None or obj.start != m.end():
            continue
        r.add(count_check(obj.entity, 0, 0, r.text[m.start():obj.end]), m.start(), obj.end, obj,
              meaning=f"no {obj.entity.label}")


RULES = (_rule_zones, _rule_wheelchair, _rule_turning, _rule_paths, _rule_view, _rule_distance, _rule_height,
         _rule_relations, _rule_counts)


def read_constraint(constraint: str, room: str = "bedroom") -> Plan:
    """Map a constraint onto checks. Unmapped words end up in ``plan.not_understood``."""
    r = _Reader(constraint, room)
    for rule in RULES:
        rule(r)
    # objects named without any requirement: they should at least be there
    used_keys = {e.key for c in r.plan.checks for e in c.entities}
    for m in r.mentions:
        if not m.used and m.entity.key not in used_keys:
            r.add(exists_check(m.entity, r.text[m.start:m.end]), m.start, m.end, m)
            used_keys.add(m.entity.key)
        r.cover(m.start, m.end)
    # objects a relation needs: a little credit for having them, so adding a missing one already pays
    counted = {e.key for c in r.plan.checks if c.kind in ("exists", "count") for e in c.entities}
    for c in list(r.plan.checks):
        for e in c.entities if c.kind in NEEDS_OBJECTS else ():
            if e.key not in counted:
                implied = exists_check(e, f"needed by {c.key}")
                implied.weight = IMPLIED_WEIGHT
                r.plan.checks.append(implied)
                r.plan.understood.append(f"{c.key} needs a {e.label} -> {implied.key} (small existence credit)")
                counted.add(e.key)
    # context words of the checks found, filler words
    kinds = {c.kind for c in r.plan.checks}
    context = set().union(*(CONTEXT_WORDS.get(k, set()) for k in kinds)) if kinds else set()
    leftovers: list[list[str]] = []
    for k, (_, _, word) in enumerate(r.words):
        if r.covered[k] or word in FILLER or word in context:
            if leftovers and leftovers[-1]:
                leftovers.append([])
            continue
        if not leftovers or not leftovers[-1] or (k > 0 and not _adjacent(r, k)):
            leftovers.append([])
        leftovers[-1].append(word)
    r.plan.not_understood.extend(" ".join(g) for g in leftovers if g)
    r.plan.checks.sort(key=lambda c: (c.weight == IMPLIED_WEIGHT, c.start))
    _unique_constants(r.plan)
    _check_room(r.plan)
    return r.plan


def _unique_constants(plan: Plan) -> None:
    """Give each check's thresholds their own names when two checks use the same one (SIDE_GAP_2, ...);
    identical softness constants are shared."""
    owner: dict[str, Param] = {}
    for check in plan.checks:
        for p in check.params:
            first = owner.setdefault(p.name, p)
            if first is p or (p.kind == "scale" and first.kind == "scale" and first.value == p.value):
                continue
            k = 2
            while f"{p.name}_{k}" in owner:
                k += 1
            new = f"{p.name}_{k}"
            check.body = re.sub(rf"\${p.name}\b", "$" + new, check.body)
            if check.curriculum == p.name:
                check.curriculum = new
            p.name = new
            owner[new] = p


def _adjacent(r: _Reader, k: int) -> bool:
    return not (r.covered[k - 1] or r.words[k - 1][2] in FILLER)


def _check_room(plan: Plan) -> None:
    """Say so when a named class does not exist in this room type (its check can never be satisfied)."""
    from iarcs_env.relations import CLASS_GROUPS
    from iarcs_env.rooms import get_room

    try:
        classes = set(get_room(plan.room).classes)
    except ValueError:  # unknown room type: the sandbox will say so
        return
    groups = set(CLASS_GROUPS)
    for check in plan.checks:
        for line in re.findall(r"scene\.(?:objects|count)\(([^)]*)\)", check.body):
            for name in re.findall(r"'([a-z_]+)'", line):
                if name not in classes and name not in groups:
                    plan.assumptions.append(f"The {plan.room} vocabulary has no '{name}'; the check "
                                            f"'{check.description}' cannot be met by that class.")


# --------------------------------------------------------------------------------------------------------
# Writing the program
# --------------------------------------------------------------------------------------------------------

HEADER = '''"""Reward program for: $constraint

Written by the iARCS offline planner. Each check returns a soft satisfaction in [0, 1] (1 when it holds,
decaying smoothly with the distance to holding); the reward is their weighted mean. The UPPER_CASE
constants are the thresholds; reflection relaxes or tightens them.
"""
import math
import torch

'''

HELPERS = '''

def clean(x):
    """A check's value as a finite float tensor in [0, 1]."""
    return torch.nan_to_num(x.float(), nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)


def soft_and(*parts):
    """Soft AND: the product (all parts together) blended with the mean (credit for each part)."""
    product, total = parts[0], parts[0]
    for part in parts[1:]:
        product = product * part
        total = total + part
    return AND_SHARE * product + (1.0 - AND_SHARE) * total / len(parts)
'''


def _fmt(value: float) -> str:
    return repr(round(float(value), 6))


def render(plan: Plan, values: dict[str, float] | None = None) -> str:
    """The reward program of a plan (every check); ``values`` override constants by name."""
    values = dict(values or {})
    checks = plan.checks
    if not checks:
        raise ValueError("no checks to write a reward program from")
    lines = [Template(HEADER).substitute(constraint=plan.constraint.replace('"""', "'''"))]
    lines.append("# Thresholds and softness of the checks")
    seen: set[str] = set()
    for c in checks:
        for p in c.params:
            if p.name not in seen:          # shared softness constants (COUNT_SCALE) are written once
                seen.add(p.name)
                lines.append(f"{p.name} = {_fmt(values.get(p.name, p.value))}  # {p.comment}")
    shared = [("AND_SHARE", 0.5, "soft AND: share of the product (the rest is the mean of the parts)")]
    if any("PARTIAL_CREDIT" in c.body for c in checks):
        shared += [("PARTIAL_CREDIT", 1, "1: add partial-credit calls with a smaller free-space radius"),
                   ("PARTIAL_SHRINK", 0.7, "radius factor of those partial-credit calls")]
    for name, default, comment in shared:
        value = values.get(name, default)
        lines.append(f"{name} = {int(value) if name == 'PARTIAL_CREDIT' else _fmt(value)}  # {comment}")
    lines.append("")
    lines.append("# Weights of the checks (relations that carry the constraint weigh more)")
    for c in checks:
        lines.append(f"W_{c.key.upper()} = {_fmt(values.get('W_' + c.key.upper(), c.weight))}")
    lines.append(HELPERS)
    for c in checks:
        body = Template(c.body).substitute({p.name: p.name for p in c.params})
        doc = textwrap.fill(c.description[0].upper() + c.description[1:] + ".", width=110,
                            initial_indent='    """', subsequent_indent="    ") + '"""'
        lines.append(f"\ndef check_{c.key}(scene):\n{doc}\n{body}")
    terms = [f"W_{c.key.upper()} * clean(check_{c.key}(scene))" for c in checks]
    total = " + ".join(f"W_{c.key.upper()}" for c in checks)
    lines.append("\ndef reward(scene):\n    \"\"\"Weighted mean of the checks, in [0, 1].\"\"\"\n"
                 "    total = (" + "\n             + ".join(terms) + ")\n"
                 f"    return total / ({total})\n")
    return "\n".join(lines)


def program_constants(code: str) -> dict[str, float]:
    """Module-level ``NAME = number`` constants of a program (UPPER_CASE names only)."""
    out: dict[str, float] = {}
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return out
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            name = node.targets[0].id
            if name.isupper():
                try:
                    value = ast.literal_eval(node.value)
                except ValueError:
                    continue
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    out[name] = float(value)
    return out


# --------------------------------------------------------------------------------------------------------
# The planner
# --------------------------------------------------------------------------------------------------------

#: Reflection: success below LOW and not rising is failing; at or above HIGH it is time to tighten.
LOW_SUCCESS = 0.15
HIGH_SUCCESS = 0.6
MIN_GAIN = 0.02
WINDOW = 6
CURRICULUM_STEPS = 2


def success_trend(success: list[float]) -> tuple[str, str]:
    """Classify a task success series as ``unknown``, ``failing``, ``rising``, ``high`` or ``flat``, with
    the numbers behind it. Rising = the later half of the last WINDOW evaluations beats the earlier half
    by more than MIN_GAIN and by more than two standard errors of the difference."""
    values = [float(v) for v in success if v is not None and math.isfinite(float(v))]
    if len(values) < 2:
        return "unknown", f"only {len(values)} evaluation(s) of task success so far"
    window = values[-WINDOW:]
    half = len(window) // 2
    early, late = window[:half], window[half:]
    m1, m2 = sum(early) / len(early), sum(late) / len(late)

    def var(xs, m):
        return sum((x - m) ** 2 for x in xs) / max(len(xs) - 1, 1)

    se = math.sqrt(var(early, m1) / len(early) + var(late, m2) / len(late))
    gain = m2 - m1
    facts = (f"task success {', '.join(f'{v:.1%}' for v in window)}: later half {m2:.1%} vs earlier half "
             f"{m1:.1%} (gain {gain:+.1%}, 2 s.e. {2 * se:.1%})")
    if window[-1] >= HIGH_SUCCESS:
        return "high", facts
    if gain > max(MIN_GAIN, 2 * se):
        return "rising", facts
    if m2 < LOW_SUCCESS:
        return "failing", facts
    return "flat", facts


class OfflinePlanner:
    """The deterministic, offline reward-synthesis agent (see the module docstring)."""

    source = "offline"

    def plan(self, room: str, constraint: str) -> Plan:
        """The checks for a constraint; raises ValueError when nothing in it can be measured."""
        if not constraint or not constraint.strip():
            raise ValueError("empty constraint: nothing to write a reward for")
        plan = read_constraint(constraint, room)
        if not plan.checks:
            raise ValueError(
                f"the offline planner could not map any part of {constraint!r} onto a measurable check "
                f"(not understood: {', '.join(plan.not_understood) or 'everything'}). It knows objects such as "
                f"{', '.join(sorted({e.label for e in OBJECTS.values()}))} and requirements such as counts, "
                f"heights ('within a 1.0 m reach'), 'on either side of', 'left/right of', 'in front of', "
                f"'facing', 'view ... from', 'within X m of', 'against the wall', 'parallel to the walls', "
                f"'wheelchair-accessible', 'turning circle', 'clear path', 'study zone'.")
        return plan

    def synthesize(self, room: str, constraint: str, feedback: str | None = None) -> RewardProposal:
        """A reward program for the constraint. With ``feedback`` (a sandbox failure of a previous try) the
        program is written in its conservative form (no extra partial-credit free-space calls)."""
        plan = self.plan(room, constraint)
        values = {"PARTIAL_CREDIT": 0} if feedback else {}
        code = render(plan, values)
        notes = ""
        if feedback:
            notes = (f"Previous attempt failed: {feedback.strip()[:300]}. Wrote the conservative form: every "
                     f"check is NaN-guarded and clamped, and the extra free-space calls are off.")
        return RewardProposal(constraint=constraint, reasoning=self.reasoning(plan), decomposition=self.decompose(plan),
                              code=code, weight=1.0, room=room, source=self.source,
                              not_understood=list(plan.not_understood), notes=notes)

    # -- explanation ----------------------------------------------------------------------------------
    @staticmethod
    def decompose(plan: Plan, values: dict[str, float] | None = None) -> list[str]:
        out = []
        for c in plan.checks:
            consts = ", ".join(f"{p.name}={_fmt((values or {}).get(p.name, p.value))}"
                               for p in c.params if p.kind == "threshold")
            weight = (values or {}).get(f"W_{c.key.upper()}", c.weight)
            out.append(f"{c.key} (weight {weight:g}): {c.description}" + (f" [{consts}]" if consts else ""))
        return out

    @staticmethod
    def reasoning(plan: Plan) -> str:
        parts = [f"Constraint: {plan.constraint!r} in a {plan.room}."]
        parts.append("Understood: " + "; ".join(plan.understood) + ".")
        parts.extend(plan.assumptions)
        parts.append(
            f"I measure it with {len(plan.checks)} check(s): "
            + ", ".join(c.key for c in plan.checks) + ". Each returns a soft satisfaction in [0, 1] that "
            "rises as the scene gets closer to the target (exponential decay outside the thresholds, soft AND "
            "= product blended with the mean), so training gets partial credit instead of a 0/1 signal; the "
            "reward is their weighted mean.")
        roles = {PRIMARY_WEIGHT: "the requirement itself", SUPPORT_WEIGHT: "a count or object the user named",
                 IMPLIED_WEIGHT: "objects a relation needs, a little credit for having them"}
        weights = sorted({c.weight for c in plan.checks}, reverse=True)
        if len(weights) > 1:
            parts.append("Weights: " + "; ".join(
                f"{', '.join(c.key for c in plan.checks if c.weight == w)} {w:g} ({roles.get(w, 'custom')})"
                for w in weights) + ".")
        elif len(plan.checks) > 1:
            parts.append("The checks weigh the same: each is one part of the requirement.")
        if plan.not_understood:
            parts.append("Ignored (no measurable meaning in my vocabulary, not guessed): "
                         + ", ".join(repr(w) for w in plan.not_understood) + ".")
        return " ".join(parts)

    # -- reflection -----------------------------------------------------------------------------------
    def reflect(self, context: ReflectionContext) -> RewardProposal:
        """A revised proposal from training feedback (see the module docstring); ``notes`` says why."""
        old = context.proposal
        try:
            plan = self.plan(old.room, old.constraint)
        except ValueError as err:
            return RewardProposal(**{**old.to_dict(), "notes": f"Stage {context.stage}: the offline planner cannot "
                                     f"revise this program ({err}); keeping it unchanged."})
        mine = old.source == self.source
        values = program_constants(old.code) if mine else {}
        # a program of mine without one of the plan's checks (an earlier planner version dropped it)
        missing = [c.key for c in plan.checks if mine and f"def check_{c.key}(" not in old.code]
        curriculum = dict(old.curriculum or {}) if mine else {}
        success = list(context.task_success)
        changed_at = curriculum.get("changed_at")
        if changed_at is not None and not 0 < changed_at <= len(success):   # a history that does not match
            changed_at = None
        since = success[max(changed_at - 1, 0):] if changed_at is not None else success
        trend, facts = success_trend(since)
        notes = [f"Stage {context.stage}: {facts}" + (" (since the last change)." if changed_at is not None else ".")]
        task_stats = context.component_stats.get("task", {})
        if task_stats:
            notes.append(f"Task reward mean {task_stats.get('mean', float('nan')):.3f} "
                         f"(max {task_stats.get('max', float('nan')):.3f}).")
        problems = [m for m in context.sandbox_messages if m]

        if problems:
            action = self._safer(values, problems, mine, notes)
        elif trend == "high":
            action = self._tighten(plan, values, curriculum, notes, reason="success is high")
        elif trend == "rising":
            action = "keep"
            notes.append("Success is rising: keep the program unchanged.")
        elif trend == "failing" and changed_at is not None and len(success) - changed_at < 2:
            action = "keep"
            notes.append(f"Only {len(success) - changed_at} evaluation(s) since the last change: too early to "
                         f"judge it, keep it.")
        elif trend == "failing" and success_trend(task_stats.get("values", []))[0] == "rising":
            action = "keep"
            notes.append("Success is low, but the task reward is still climbing: give it time, keep the program.")
        elif trend == "failing":
            action = self._relax(plan, values, curriculum, notes)
        elif trend == "flat" and curriculum.get("stage", 0) < len(curriculum.get("values", [])) - 1:
            action = self._tighten(plan, values, curriculum, notes,
                                   reason="success has settled at the relaxed stage")
        else:
            action = "keep"
            notes.append("Not enough evidence to change the reward: keep it." if trend == "unknown" else
                         "Success is flat but not failing and there is nothing to tighten: keep it.")
        if missing:
            notes.append(f"The program in use lacks {', '.join(missing)} (dropped by an earlier planner version): "
                         f"bring it back, a reward without a check the constraint requires stops measuring it.")
            action = "restore" if action == "keep" else action
        code = old.code
        if action != "keep":
            code = render(plan, values)
            if curriculum:
                curriculum["changed_at"] = len(success)
            if code == old.code:
                action = "keep"
        return RewardProposal(constraint=old.constraint, reasoning=self.reasoning(plan) + f" Reflection: {action}.",
                              decomposition=self.decompose(plan, values), code=code, weight=old.weight,
                              room=old.room, source=self.source, not_understood=list(plan.not_understood),
                              curriculum=curriculum, notes=" ".join(notes))

    @staticmethod
    def _safer(values: dict, problems: list[str], mine: bool, notes: list[str]) -> str:
        """Sandbox failures: the guarded program, without the extra free-space calls."""
        notes.append(f"The sandbox reported {len(problems)} problem(s) (last: {problems[-1][:200]}).")
        if not mine:
            notes.append("The program in use was not written by me: replace it by the planner's guarded program "
                         "(every check NaN-guarded and clamped to [0, 1]).")
        if "PARTIAL_CREDIT" in values and values["PARTIAL_CREDIT"]:
            values["PARTIAL_CREDIT"] = 0
            notes.append("Safer program: the extra partial-credit free-space calls are off (fewer grid "
                         "computations, less time and memory per batch); thresholds kept.")
        elif mine:
            notes.append("My program already guards every check (clean(): NaN -> 0, clamp to [0, 1]) and makes "
                         "no optional expensive calls: nothing safer to write, keep it.")
            return "keep"
        return "safer"

    @staticmethod
    def _primary(plan: Plan) -> tuple[Check, Param] | None:
        for c in sorted(plan.checks, key=lambda c: -c.weight):
            if c.curriculum:
                return c, next(p for p in c.params if p.name == c.curriculum)
        return None

    def _relax(self, plan: Plan, values: dict, curriculum: dict, notes: list[str]) -> str:
        """Failing: start a curriculum, step it back, simplify (softer, denser terms), then emphasise the checks
        that need the constraint's objects (see :meth:`_emphasise`). Never drops a check."""
        target = self._primary(plan)
        if not curriculum and target is not None:
            check, p = target
            steps = [round(p.value + p.relax * k, 6) for k in range(CURRICULUM_STEPS, -1, -1)]
            curriculum.update(parameter=p.name, values=steps, stage=0, target=p.value)
            values[p.name] = steps[0]
            notes.append(f"Success is low and not improving: the reward is failing. Curriculum on {p.name} "
                         f"({p.comment}): start relaxed at {steps[0]:g}, tighten over later stages through "
                         f"{', '.join(f'{v:g}' for v in steps[1:])} (the target).")
            return "curriculum"
        if curriculum.get("stage", 0) > 0:
            curriculum["stage"] -= 1
            values[curriculum["parameter"]] = curriculum["values"][curriculum["stage"]]
            notes.append(f"Success fell back after tightening: step the curriculum back to "
                         f"{curriculum['parameter']} = {values[curriculum['parameter']]:g}.")
            return "curriculum"
        if values.get("AND_SHARE", 0.5) >= 0.5:
            for c in plan.checks:
                for p in c.params:
                    if p.kind == "scale":
                        values[p.name] = p.value * 2
            values["AND_SHARE"] = 0.25
            notes.append("Still failing at the most relaxed stage: simplify. The soft terms decay half as fast "
                         "(every *_SCALE doubled) and the soft AND leans on the mean of its parts (AND_SHARE "
                         "0.25), so partial progress on the hardest check earns more credit.")
            return "simplification"
        return self._emphasise(plan, values, notes)

    @staticmethod
    def _emphasised(plan: Plan) -> list[Check]:
        """The checks an emphasis step weighs up: the requirement checks that need their objects (relations,
        heights, walls, a turning circle next to an object) and the existence of the objects a relation
        needs (has_bed, ...). Counts, named objects and the checks an emptier room satisfies keep theirs."""
        return [c for c in plan.checks
                if (c.weight >= PRIMARY_WEIGHT and c.entities and c.kind not in EMPTY_ROOM_KINDS)
                or (c.kind == "exists" and c.weight == IMPLIED_WEIGHT)]

    def _emphasise(self, plan: Plan, values: dict, notes: list[str]) -> str:
        """Still failing after relaxing and simplifying: multiply the weights of :meth:`_emphasised` checks by
        EMPHASIS_FACTOR, up to EMPHASIS_CAP times their original weight; at the cap, keep the program."""
        never = ("No check is dropped: each measures part of the constraint, and a reward without one would "
                 "rise while the constraint fails.")
        targets = self._emphasised(plan)
        others = [c for c in plan.checks if c not in targets]
        if not targets or not others:
            why = ("no check needs the constraint's objects" if not targets else
                   "every check needs the constraint's objects, and raising all weights together leaves the "
                   "weighted mean unchanged")
            notes.append(f"Still failing after relaxing and simplifying; an emphasis would change nothing ({why}). "
                         f"{never} Keep the program and leave it to the next reflection (or a language model) "
                         f"to rethink the decomposition.")
            return "keep"
        raised = []
        for c in targets:
            name = f"W_{c.key.upper()}"
            now = values.get(name, c.weight)
            new = round(min(now * EMPHASIS_FACTOR, c.weight * EMPHASIS_CAP), 6)
            if new > now:
                values[name] = new
                raised.append(f"{name} {now:g} -> {new:g}")
        if not raised:
            notes.append(f"Still failing, and the checks that need the constraint's objects "
                         f"({', '.join(c.key for c in targets)}) are already at {EMPHASIS_CAP:g}x their original "
                         f"weight, the cap of the emphasis. {never} Keep the program and leave it to the next "
                         f"reflection (or a language model) to rethink the decomposition.")
            return "keep"
        rest = ", ".join(c.key for c in others) + (" keeps its" if len(others) == 1 else " keep their")
        notes.append(f"Still failing after relaxing and simplifying: emphasise the checks that need the constraint's "
                     f"objects ({'; '.join(raised)}; at most {EMPHASIS_CAP:g}x the original weight), so the reward "
                     f"pays more for them; {rest} weight. {never}")
        return "emphasis"

    def _tighten(self, plan: Plan, values: dict, curriculum: dict, notes: list[str], reason: str) -> str:
        """Move the curriculum one stage toward its target; at the target undo the simplification (an
        emphasis stays: it makes the reward measure the constraint more, not less)."""
        if curriculum.get("stage", 0) < len(curriculum.get("values", [])) - 1:
            curriculum["stage"] += 1
            values[curriculum["parameter"]] = curriculum["values"][curriculum["stage"]]
            final = curriculum["stage"] == len(curriculum["values"]) - 1
            notes.append(f"Tighten ({reason}): {curriculum['parameter']} = {values[curriculum['parameter']]:g}"
                         + (" (the final target)." if final else "."))
            return "tighten"
        if values.get("AND_SHARE", 0.5) < 0.5:
            for c in plan.checks:
                for p in c.params:
                    if p.kind == "scale":
                        values[p.name] = p.value
            values["AND_SHARE"] = 0.5
            emphasised = [c.key for c in plan.checks if values.get(f"W_{c.key.upper()}", c.weight) > c.weight]
            kept = (f"; {', '.join(emphasised)} keep their emphasised weight" if emphasised else "")
            notes.append(f"Tighten ({reason}): restore the original softness{kept}.")
            return "tighten"
        notes.append(f"{reason[0].upper() + reason[1:]} and the program is at its final target: keep it.")
        return "keep"
