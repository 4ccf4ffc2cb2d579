"""The offline planner's reader (:mod:`rewards.planner`): a natural-language constraint mapped onto the checks of
:mod:`rewards.planner_checks`; the words it cannot map are kept in ``Plan.not_understood``, never guessed."""

from __future__ import annotations

import re
from dataclasses import dataclass

from .constraint_grammar import _NUM, _UNIT, GRAMMAR_RULES, QTY, cover_all, quantity, scope
from .planner_checks import (CONTEXT_WORDS, FAR_GAP, FARSIGHTED_MIN, FILLER, FRONT_DEPTH, IMPLIED_WEIGHT,
                             IRREGULAR_PLURALS, NEAR_GAP, NEEDS_OBJECTS, NUMBER_WORDS, OBJECTS, Check, Entity, Param,
                             Plan, STUDY_SEATS, UHD_MAX, VIEW_ANGLE, VIEW_RANGE, WALKING_PATH, WALL_GAP,
                             WHEELCHAIR_PATH, WHEELCHAIR_TURN, aligned_check, clear_path_check, count_check,
                             either_side_check, exists_check, facing_check, far_check, height_check, in_front_check,
                             near_check, side_check, turning_check, view_check, wall_check)
from .planner_scope import EVERY, NONE, SOME, WITHOUT, object_check, pair_check


# --------------------------------------------------------------------------------------------------------
# Reading the constraint
# --------------------------------------------------------------------------------------------------------

#: Words that may stand between a relation and the object it names ("facing the bed", "next to every bed").
_DETERMINERS = re.compile(r" ?(?:(?:the|a|an|its|their|my|our|this|that|these|those|any|every|each|all|some|both|2|"
                          r"of|one) )*")


#: A preposition (and determiners) just before an object word: the object of a relation, not a subject.
_OBJECT_OF = re.compile(r"\b(?:of|to|from|facing|faces|face|behind|beside|near|between|towards?|than|against|by|"
                        r"opposite)(?: (?:the|a|an|its|their|any|every|each|all|some|both|2|1))* $")
#: ... unless a quantifier owns the "of" ("none of the chairs", "each of the beds").
_QUANTIFIER_OF = re.compile(r"\b(?:none|all|each|any|some|every|both|1|2) of(?: the)? $")


#: Two objects joined by "and" / "or".
_AND_OR = re.compile(r" (?:and|or) (?:the |a |an )?")


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
        self.objects_of: dict[int, str] = {}

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
            plural = IRREGULAR_PLURALS.get(phrase, phrase + "s")
            pattern = rf"\b(?:{re.escape(plural)}|{re.escape(phrase)}(?:es)?)\b"
            for m in re.finditer(pattern, self.text):
                if not any(m.start() < f.end and f.start < m.end() for f in found):
                    found.append(_Mention(m.start(), m.end(), OBJECTS[phrase]))
        return sorted(found, key=lambda f: f.start)

    def before(self, pos: int, exclude: Entity | None = None, subject: bool = True) -> _Mention | None:
        """The last object named before ``pos``; as a ``subject``, not one that is the object of a preposition
        ("... beside the bed, not in front of it": the bed is not what should not be in front)."""
        cands = [m for m in self.mentions if m.end <= pos and m.entity != exclude]
        if not cands:
            return None
        head = self.text[:cands[-1].start]
        if subject and _OBJECT_OF.search(head) and not _QUANTIFIER_OF.search(head):
            return None
        return cands[-1]

    def after(self, pos: int, limit: int | None = None) -> _Mention | None:
        cands = [m for m in self.mentions if m.start >= pos and (limit is None or m.start < limit)]
        return cands[0] if cands else None

    def reference_after(self, pos: int, subject: _Mention | None) -> _Mention | None:
        """The object named right after a relation (only determiners between); ``it``/``them`` refer back to the
        object before the subject."""
        rest = self.text[pos:].lstrip()
        if re.match(r"(?:it|them)\b", rest) and subject is not None:
            self.cover(pos, pos + len(self.text[pos:]) - len(rest) + 4)
            return self.before(subject.start, exclude=subject.entity, subject=False)
        words = _DETERMINERS.match(self.text, pos)
        return next((m for m in self.mentions if m.start == words.end()), None)

    def add(self, check: Check, start: int, end: int, *mentions: _Mention | None, meaning: str = "") -> None:
        for m in mentions:
            if m is not None:
                m.used = True
                self.cover(m.start, m.end)
        for m in mentions[1:]:  # the objects of a relation (after its subject), and the phrase that names them
            if m is not None:
                self.objects_of[m.start] = self.text[start:end]
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
            if "deg" in m.group("q") or _read(r, m.start(), m.end()):
                continue
            subject = r.before(m.start())
            if subject is None:
                r.plan.not_understood.append(f"{m.group()} (no object named before it)")
                r.cover(m.start(), m.end())
                continue
            quant, spans = scope(r, subject, m.start())
            if quant not in (None, EVERY):
                continue                 # "no shelf ...", "not ...": not read
            cover_all(r, spans)
            r.add(height_check(subject.entity, quantity(m.group("q")), m.group()), m.start(), m.end(), subject)


def _rule_distance(r: _Reader) -> None:
    near_q = rf"\b(?:within|at most|no more than|less than|no farther than) (?P<q>{QTY}) (?:away )?(?:of|from)\b"
    far_q = (rf"\b(?:at least|no less than|more than|minimum of) (?P<q>{QTY}) (?:away )?from\b|"
             rf"\b(?P<q2>{QTY}) (?:or more )?away from\b")
    near_w = r"\b(?:next to|beside|near|close to|adjacent to|alongside)\b"
    far_w = r"\b(?:far (?:away )?from|(?:well )?away from)\b"
    for pattern, kind in ((near_q, "near"), (far_q, "far"), (near_w, "near_word"), (far_w, "far_word")):
        for m in re.finditer(pattern, r.text):
            if any(r.covered[k] for k, (s, e, _) in enumerate(r.words) if s >= m.start() and e <= m.end()):
                continue
            subject, ref = r.before(m.start()), None
            ref = r.reference_after(m.end(), subject)
            if subject is None or ref is None:
                r.plan.not_understood.append(f"'{m.group()}' (needs an object before and after it)")
                r.cover(m.start(), m.end())
                continue
            quant, spans = scope(r, subject, m.start())
            if kind in ("far", "far_word"):
                if quant in (NONE, WITHOUT):     # "no X at least d from Y": not read
                    continue
                dist = quantity(m.group("q") or m.group("q2")) if kind == "far" else FAR_GAP
                check = far_check(subject.entity, ref.entity, dist, m.group())
            else:
                dist = quantity(m.group("q")) if kind == "near" else NEAR_GAP
                check = (near_check(subject.entity, ref.entity, dist, m.group()) if quant in (None, SOME) else
                         pair_check("far" if quant == NONE else "near", subject.entity, ref.entity,
                                    quant, dist, m.group()))   # NONE: no pair within dist
            cover_all(r, spans)
            r.add(check, m.start(), m.end(), subject, ref)


def _rule_relations(r: _Reader) -> None:
    rules = [
        (r"\b(?:on |at )?(?:either|both|each|opposite) sides? of\b|\bflank(?:ing|ed|s)?\b|\bon each side of\b",
         "either_side"),
        (r"\b(?:on |to )?(?:the )?left(?: hand)?(?: side)? of\b", "left"),
        (r"\b(?:on |to )?(?:the )?right(?: hand)?(?: side)? of\b", "right"),
        (r"\bin front of\b", "in_front"),
        (r"\bfac(?:ing|es|e)(?! away)(?: towards?| to)?\b", "facing"),
        (r"\b(?:against|along|touching|flush with|backed (?:up )?against|with (?:its|their) backs? (?:to|against)) "
         r"(?:the |a |one )?walls?\b", "wall"),
        (r"\b(?:parallel (?:to|with)|aligned (?:to|with)|square (?:to|with)|straight (?:to|with)) (?:the |a |its )?"
         r"walls?\b", "aligned"),
    ]
    for pattern, kind in rules:
        for m in re.finditer(pattern, r.text):
            if _read(r, m.start(), m.end()):
                continue
            subject = r.before(m.start())
            if kind in ("wall", "aligned"):
                if subject is None:
                    r.plan.not_understood.append(f"'{m.group()}' (no object named before it)")
                    r.cover(m.start(), m.end())
                    continue
                quant, spans = scope(r, subject, m.start())
                if kind == "aligned" and quant in (None, EVERY):
                    check = aligned_check(subject.entity, m.group())
                elif kind == "wall" and quant in (None, EVERY):
                    check = wall_check(subject.entity, m.group())
                elif kind == "wall":     # "a chair against the wall", "the bed not against a wall"
                    check = object_check("wall", subject.entity, quant, WALL_GAP, m.group())
                else:
                    continue
                cover_all(r, spans)
                r.add(check, m.start(), m.end(), subject)
                continue
            ref = r.reference_after(m.end(), subject)
            if subject is None or ref is None:
                r.plan.not_understood.append(f"'{m.group()}' (needs an object before and after it)")
                r.cover(m.start(), m.end())
                continue
            s, o = subject.entity, ref.entity
            quant, spans = scope(r, subject, m.start())
            if quant is not None and kind in ("either_side", "left", "right"):
                continue                 # their words stay uncovered: not read with a quantifier or a negation
            cover_all(r, spans)
            if quant is not None:
                angle = re.compile(rf"\bwithin (?P<q>{_NUM}) ?deg(?:rees?)?\b").match(r.text, ref.end + 1)
                if angle:
                    r.cover(angle.start(), angle.end())
                value = (float(angle.group("q")) if angle else VIEW_ANGLE) if kind == "facing" else FRONT_DEPTH
                r.add(pair_check(kind, s, o, quant, value, m.group()), m.start(), m.end(), subject, ref)
                continue
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
        if obj is None or obj.start != m.end() or _read(r, m.start(), m.end()):
            continue
        n, mode = int(m.group("n")), quals.get(m.group("qual") or "", "plain")
        if mode != "plain" and obj.used and _relation_follows(r, obj.end):
            continue    # "at least 3 chairs against a wall": a count of the chairs meeting it, not read
        lo, hi = {"min": (n, None), "more": (n + 1, None), "max": (0, n), "less": (0, max(n - 1, 0)),
                  "exact": (n, n), "plain": (n, None)}[mode]
        if mode == "plain":
            r.plan.assumptions.append(f"'{m.group('n')} {r.text[obj.start:obj.end]}' read as at least {n} "
                                      f"(an extra one elsewhere does not break the request).")
        r.add(count_check(obj.entity, lo, hi, r.text[m.start():obj.end]), m.start(), obj.end, obj)
    for m in re.finditer(r"\b(?:no|without(?: (?:a|an|any))?)\b (?=[a-z])", r.text):
        obj = r.after(m.end())
        if obj is None or obj.start != m.end() or obj.used or _read(r, m.start(), m.end()):
            continue
        r.add(count_check(obj.entity, 0, 0, r.text[m.start():obj.end]), m.start(), obj.end, obj,
              meaning=f"no {obj.entity.label}")


def _relation_follows(r: _Reader, pos: int) -> bool:
    """The next words read after ``pos`` (a relation) follow in the same clause (no "and" before them)."""
    nxt = next((s for k, (s, e, _) in enumerate(r.words) if s >= pos and r.covered[k]), None)
    return nxt is not None and " and " not in r.text[pos:nxt + 1]


def _read(r: _Reader, start: int, end: int) -> bool:
    """Some word between ``start`` and ``end`` was already read by another rule."""
    return any(r.covered[k] for k, (s, e, _) in enumerate(r.words) if s >= start and e <= end)


RULES = (_rule_zones, _rule_wheelchair, _rule_turning, _rule_paths, _rule_view, *GRAMMAR_RULES, _rule_distance,
         _rule_height, _rule_relations, _rule_counts)


def read_constraint(constraint: str, room: str = "bedroom") -> Plan:
    """Map a constraint onto checks. Unmapped words end up in ``plan.not_understood``."""
    r = _Reader(constraint, room)
    for rule in RULES:
        rule(r)
    # "facing the bed and the wardrobe": a second object of a relation, not read (to either or to both?)
    for before, m in zip(r.mentions, r.mentions[1:]):
        if not m.used and before.start in r.objects_of and _AND_OR.fullmatch(r.text[before.end:m.start]):
            r.plan.not_understood.append(f"'{r.objects_of[before.start]} ... {r.text[before.end:m.end].strip()}' "
                                         f"(a relation to either or to both: not read)")
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
        needed = c.entities[1:] if c.scope == WITHOUT else () if c.scope == NONE else c.entities
        for e in needed if c.kind in NEEDS_OBJECTS else ():
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
