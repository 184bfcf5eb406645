"""Which of the checked verbs a sentence asks for ("a person jumps over a puddle" -> jump).

One table for the whole project: the data's README counts hours per verb with it, the physical checks are
calibrated on the real clips it finds, and the vocabulary benchmark (``scripts/vocabulary.py``) picks its test
captions with it. A verb here has a physical check of the same name (``mld_core.eval.physical.shows``).
"""

from __future__ import annotations

import re

# verb -> the words that ask for it (regular expressions over the lower-cased sentence).
VERB_PATTERNS = {
    "jump": r"\b(jump\w*|(?<!lindy )(?<!hip )hops?|hopp\w*|leap\w*|hopscotch|bounc\w+ on)\b",
    "get_low": r"\b(sit|sits|sitting|sat|squat\w*|kneel\w*|knelt|crouch\w*|ducks?(?![ -]foot)|ducking)\b",
    "on_ground": r"\b(lie|lies|lying|lay|lays|laying|fall|falls|falling|fell|collaps\w*|on the (floor|ground))\b",
    "crawl": r"\b(?<!front )(crawl\w*)\b(?! (movements|swimming|stroke))",
    "reach_floor": r"\b(pick\w* (up|\w+ up)|picks? up|scoop\w*)\b",
    "inverted": r"\b(cartwheel\w*|handstand\w*|hand ?spring|back ?flip\w*|flip\w*|somersault\w*|summersult)\b",
    "stand_up": r"\b(stand\w* up|get\w* up|gets up|got up|rises|rising|stands back up)\b",
    "climb": r"\b(climb\w*|ladder|up (the )?stairs|upstairs)\b",
    "kick": r"\b(kick\w*)\b",
    "throw": r"\b(throw(?!\w* punch)\w*|threw|toss\w*|pitch\w*)\b",
}
_COMPILED = {verb: re.compile(pattern) for verb, pattern in VERB_PATTERNS.items()}
VERBS = tuple(VERB_PATTERNS)
# verb -> what a take shows when it shows the verb, for the notes a user reads ("it does not show a jump").
VERB_SHOWN = {"jump": "a jump", "get_low": "getting low (a squat, a sit, a crouch)", "on_ground": "lying on the ground",
              "crawl": "a crawl", "reach_floor": "a reach down to the floor", "inverted": "the body upside down",
              "stand_up": "standing up from the ground", "climb": "a climb", "kick": "a kick", "throw": "a throw"}


def verbs_in(text: str) -> list[str]:
    """The checked verbs ``text`` asks for, in the table's order."""
    lower = str(text).lower()
    return [verb for verb, pattern in _COMPILED.items() if pattern.search(lower)]


def verbs_in_order(text: str) -> list[str]:
    """The checked verbs ``text`` asks for, in the order it first names them ("stands up from sitting on the ground":
    stand_up, get_low, on_ground)."""
    lower = str(text).lower()
    found = [(m.start(), i, verb) for i, (verb, pattern) in enumerate(_COMPILED.items())
             if (m := pattern.search(lower))]
    return [verb for _, _, verb in sorted(found)]
