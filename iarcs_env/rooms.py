"""Room specifications: class lists and slot counts of the 3D-FRONT room types (ATISS conventions).

Each room type has an ordered list of object classes and a number of object slots N.  The model's
class vocabulary is ``classes + ["empty"]`` (K = len(classes) + 1), where ``empty`` marks an unused slot.
"""

from __future__ import annotations

from dataclasses import dataclass

BEDROOM_CLASSES = (
    "armchair", "bookshelf", "cabinet", "ceiling_lamp", "chair", "children_cabinet", "coffee_table",
    "desk", "double_bed", "dressing_chair", "dressing_table", "kids_bed", "nightstand", "pendant_lamp",
    "shelf", "single_bed", "sofa", "stool", "table", "tv_stand", "wardrobe",
)
LIVING_DINING_CLASSES = (
    "armchair", "bookshelf", "cabinet", "ceiling_lamp", "chaise_longue_sofa", "chinese_chair",
    "coffee_table", "console_table", "corner_side_table", "desk", "dining_chair", "dining_table",
    "l_shaped_sofa", "lazy_sofa", "lounge_chair", "loveseat_sofa", "multi_seat_sofa", "pendant_lamp",
    "round_end_table", "shelf", "stool", "tv_stand", "wardrobe", "wine_cabinet",
)
EMPTY = "empty"
#: Classes that hang from the ceiling: not "ground objects" for collision, reachability and walkability.
CEILING_CLASSES = frozenset({"ceiling_lamp", "pendant_lamp"})


@dataclass(frozen=True)
class RoomSpec:
    """One room type: ``name`` (as in the data files), its object ``classes`` and ``max_objects`` slots."""

    name: str
    classes: tuple[str, ...]
    max_objects: int
    gym_name: str

    @property
    def vocabulary(self) -> tuple[str, ...]:
        """Classes plus ``empty`` (the last index), the K of the model features."""
        return self.classes + (EMPTY,)

    @property
    def num_classes(self) -> int:
        """K: object classes plus ``empty``."""
        return len(self.classes) + 1

    @property
    def empty_index(self) -> int:
        return len(self.classes)

    @property
    def feature_dim(self) -> int:
        """Per-slot model feature size: translation 3 + size 3 + [cos, sin] 2 + one-hot K."""
        return 8 + self.num_classes

    def class_index(self, label: str) -> int:
        try:
            return self.classes.index(label)
        except ValueError:
            raise ValueError(
                f"unknown {self.name} class {label!r}; known classes: {', '.join(self.classes)}"
            ) from None

    def ground_mask(self):
        """Boolean list over the vocabulary: True for ground objects (not ceiling lamps, not empty)."""
        return [c not in CEILING_CLASSES and c != EMPTY for c in self.vocabulary]


ROOMS: dict[str, RoomSpec] = {
    "bedroom": RoomSpec("bedroom", BEDROOM_CLASSES, 12, "Bedroom"),
    "livingroom": RoomSpec("livingroom", LIVING_DINING_CLASSES, 21, "LivingRoom"),
    "diningroom": RoomSpec("diningroom", LIVING_DINING_CLASSES, 21, "DiningRoom"),
}


def get_room(name: str | RoomSpec) -> RoomSpec:
    """Look a room type up by name; accepts ``living_room``, ``living-room``, ``LivingRoom`` too."""
    if isinstance(name, RoomSpec):
        return name
    key = str(name).lower().replace("_", "").replace("-", "").replace(" ", "")
    if key not in ROOMS:
        raise ValueError(f"unknown room type {name!r}; choose one of: {', '.join(ROOMS)}")
    return ROOMS[key]
