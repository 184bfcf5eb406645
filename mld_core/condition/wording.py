"""A command worded as the training captions word a motion: "jump" -> "a person jumps".

Every training caption describes a person ("a person jumps over an obstacle"), while users often type a bare
command ("jump", "crawl", "wave your right hand"). The frozen sentence encoder reads the two far apart (MiniLM: cos
0.67-0.83 between "crawl" and "a person crawls"), so the denoiser sees a command as a text unlike any it trained on.
``as_sentence`` gives a command the captions' subject and puts its verb in the third person (cos 0.95-0.99), which
is what the prompt meant. A text that already starts like a sentence about someone is left as it is; so is one
whose first word is no verb this can conjugate safely (a number, a word with digits or hyphens).
"""

from __future__ import annotations

import re

SUBJECT = "a person"
SUBJECT_WORDS = frozenset("a an the person someone man woman".split())
# Words a sentence about a person starts with: such a text is a description already, not a command.
SENTENCE_STARTS = SUBJECT_WORDS | frozenset("""
somebody he she they people human figure character actor dancer guy girl boy child kid his her their this
""".split())
# Verbs ending in -ing that are no gerund ("bring the box" is a command, "running" a description).
_ING_VERBS = frozenset("bring cling fling ring sing sling spring sting string swing wring".split())
_IRREGULAR = {"be": "is", "have": "has", "do": "does", "go": "goes", "are": "is"}
_DROPPED = frozenset({"please", "now", "just"})  # politeness and fillers before a command's verb
_POSSESSIVE = {"your": "their", "yours": "theirs", "yourself": "themselves"}
_WORD = re.compile(r"[A-Za-z]+(?:'[a-z]+)?")
_ES_ENDINGS = ("s", "sh", "ch", "x", "z", "o")


def third_person(verb: str) -> str:
    """The verb's present third person singular ("kick" -> "kicks", "crouch" -> "crouches", "fly" -> "flies");
    a word that already ends in a single s ("walks") is taken as conjugated."""
    lower = verb.lower()
    if lower in _IRREGULAR:
        return _IRREGULAR[lower]
    if lower.endswith("s") and not lower.endswith("ss"):
        return verb
    if lower.endswith("y") and len(lower) > 1 and lower[-2] not in "aeiou":
        return verb[:-1] + "ies"
    if lower.endswith(_ES_ENDINGS):
        return verb + "es"
    return verb + "s"


def is_command(text: str) -> bool:
    """Whether ``text`` reads as a bare command: its first word is not one a sentence about someone starts with."""
    words = text.split()
    first = _first_word(words[0]) if words else None
    return first is not None and first not in SENTENCE_STARTS


def _first_word(token: str) -> str | None:
    match = _WORD.fullmatch(token.strip(".,;:!?\"'()"))
    return match.group(0).lower() if match else None


def as_sentence(text: str) -> str:
    """``text`` as a caption would word it: a bare command gets the subject and its verb in the third person
    ("Jump!" -> "a person jumps!", "please wave your left hand" -> "a person waves their left hand", "walking
    backwards" -> "a person is walking backwards"); any other text is returned unchanged."""
    words = text.split()
    while len(words) > 1 and _first_word(words[0]) in _DROPPED:
        words = words[1:]
    if not words or not is_command(" ".join(words)):
        return text
    lead = words[0].strip(".,;:!?\"'()")
    tail = words[0][len(words[0].rstrip(".,;:!?\"'()")):]  # punctuation after the verb ("Jump!")
    verb = lead.lower()
    if verb.endswith("ly") and len(words) > 1:  # "slowly walk forward": the verb comes second
        rest = as_sentence(" ".join(words[1:]))
        return rest.replace(SUBJECT, f"{SUBJECT} {words[0].lower()}", 1) if rest.startswith(SUBJECT) else text
    gerund = verb.endswith("ing") and len(verb) > 4 and verb not in _ING_VERBS
    conjugated = f"is {verb}" if gerund else third_person(verb)
    rest = [_POSSESSIVE.get(w.lower(), w) for w in words[1:]]
    return " ".join([SUBJECT, conjugated + tail, *rest])
