"""Self-contained reading of object descriptions for textual fidelity (§8.2).

Descriptions are short noun phrases ("a red sedan", "a flatbed truck hauling a load of fir trees").
Without a VLM, the judge checks the two things such a phrase pins down that a crop can show: the
colour word and the category word. :func:`parse_description` maps them onto
:data:`~world_model.scene.NAMED_COLORS` and :data:`~world_model.scene.CATEGORIES`; the judge then asks
its colour and category heads about them. Longest phrases win ("dark red" before "red", "cement
mixer truck" before "truck").
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from world_model.scene import CATEGORIES, NAMED_COLORS

# Words and phrases naming each category (lower case). Multi-word phrases are matched first.
CATEGORY_WORDS: dict[str, tuple[str, ...]] = {
    "car": ("car", "sedan", "hatchback", "suv", "station wagon", "coupe", "convertible", "taxi"),
    "truck": ("truck", "box truck", "semi-trailer truck", "semi", "lorry", "pickup"),
    "bus": ("bus", "city bus", "coach"),
    "van": ("van", "delivery van", "minivan"),
    "motorcycle": ("motorcycle", "motorbike", "scooter"),
    "cyclist": ("cyclist", "bicycle", "bike", "bicyclist"),
    "pedestrian": ("pedestrian", "person", "walker", "man", "woman", "child"),
    "cone": ("cone", "traffic cone"),
    "barrier": ("barrier", "road barrier", "guardrail"),
    "tree_truck": ("trees", "tree", "fir trees", "logs", "truck hauling"),
    "cement_mixer": ("cement mixer", "cement", "concrete mixer", "mixer"),
}

# Colour words beyond the named colours' own names ("dark_red" is also "dark red").
COLOR_SYNONYMS: dict[str, str] = {"grey": "gray", "maroon": "dark_red", "tan": "beige", "violet": "purple"}


@dataclass(frozen=True)
class ParsedDescription:
    """What a description says about an object: a category and a named colour, each optional."""

    category: str | None
    color: str | None

    @property
    def empty(self) -> bool:
        return self.category is None and self.color is None


def _phrase_table() -> list[tuple[str, str, str]]:
    """(phrase, kind, value) sorted longest phrase first."""
    table = [(w, "category", c) for c, words in CATEGORY_WORDS.items() for w in words]
    table += [(name.replace("_", " "), "color", name) for name in NAMED_COLORS]
    table += [(w, "color", c) for w, c in COLOR_SYNONYMS.items()]
    return sorted(table, key=lambda t: (-len(t[0]), t[0]))


_TABLE = _phrase_table()


def parse_description(text: str) -> ParsedDescription:
    """The first-mentioned colour and the most specific category named in ``text``.

    The category is the one named by the longest matching phrase (so "a truck hauling a load of
    trees" is a tree_truck, not a truck); the colour is the earliest colour phrase in the text.
    """
    if not isinstance(text, str):
        raise TypeError(f"description must be a string, got {type(text).__name__}")
    s = " " + re.sub(r"[^a-z]+", " ", text.lower()).strip() + " "
    used = [False] * len(s)
    category, color, color_pos = None, None, len(s)
    for phrase, kind, value in _TABLE:
        for m in re.finditer(rf"(?<= ){re.escape(phrase)}s?(?= )", s):
            if any(used[m.start() : m.end()]):
                continue
            used[m.start() : m.end()] = [True] * (m.end() - m.start())
            if kind == "category" and category is None:
                category = value
            elif kind == "color" and m.start() < color_pos:
                color, color_pos = value, m.start()
    if category is not None and category not in CATEGORIES:
        raise AssertionError(f"CATEGORY_WORDS names unknown category {category!r}")
    return ParsedDescription(category=category, color=color)
