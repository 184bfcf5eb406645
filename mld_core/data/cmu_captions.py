"""Captions for CMU trials: KIT Motion-Language sentences where there are some, CMU's one-line descriptions turned into
sentences ("playground - climb, hang, swing" -> "a person climbs, hangs and swings on a playground"), and, for long
trials whose description lists several actions, captions per window that name only the actions a physical detector
finds in that window.

A description is captioned only when its words are understood (a verb or an action noun this module knows);
cryptic ones ("clean", "Story", "Lavish", "12.5 lbs") leave the trial uncaptioned, and calibration, range-of-motion
and T-pose takes are skipped. Two-subject trials keep only what the description says this subject does.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

SKIP = re.compile(r"calibrat|range ?of ?motion|\bt-?pose\b|bad amc|lost marker|trial dont match|bad ?start ?seq")
_TWO_SUBJECTS = re.compile(r"\s*\((?:2 )?subjects? - subject ([ab])\)\s*$")
_HUMAN_SUBJECT = re.compile(r"\s*\(human subject\)\s*$")
_CLEANED = re.compile(r"\s*cleaned ?grs\s*$")

# base verb -> third person (irregular ones; the rest add -s / -es / -ies).
_IRREGULAR = {"do": "does", "go": "goes", "lie": "lies", "have": "has", "be": "is"}
# gerunds and other forms -> base verb.
_BASE = {"laying": "lie", "lying": "lie", "lay": "lie", "getting": "get", "sitting": "sit", "running": "run",
         "jogging": "jog", "hopping": "hop", "swimming": "swim", "putting": "put", "stepping": "step",
         "swinging": "swing", "dragging": "drag", "chopping": "chop", "shopping": "shop", "planting": "plant",
         "digging": "dig", "dancing": "dance", "waving": "wave", "placing": "place", "taking": "take",
         "making": "make", "bouncing": "bounce", "shaking": "shake", "mixing": "mix", "raking": "rake",
         "closing": "close", "opening": "open", "hammering": "hammer", "drinking": "drink", "eating": "eat",
         "walking": "walk", "jumping": "jump", "kicking": "kick", "punching": "punch", "stretching": "stretch",
         "climbing": "climb", "crawling": "crawl", "picking": "pick", "throwing": "throw", "pushing": "push",
         "pulling": "pull", "carrying": "carry", "sweeping": "sweep", "washing": "wash", "cleaning": "clean",
         "looking": "look", "searching": "search", "marching": "march", "sneaking": "sneak", "turning": "turn",
         "standing": "stand", "pivoting": "pivot", "waiting": "wait", "answering": "answer", "dialing": "dial",
         "painting": "paint", "sewing": "sew", "shaving": "shave", "slicing": "slice", "sawing": "saw",
         "screwing": "screw", "unscrewing": "unscrew", "typing": "type", "writing": "write", "fishing": "fish",
         "rowing": "row", "driving": "drive", "drumming": "drum", "laughing": "laugh", "crying": "cry",
         "arguing": "argue", "flexing": "flex", "peeping": "peep", "ducking": "duck", "limping": "limp",
         "creeping": "creep", "shooting": "shoot", "holding": "hold", "hanging": "hang", "coiling": "coil",
         "vacuuming": "vacuum", "teaching": "teach", "sipping": "sip", "chugging": "chug", "combing": "comb",
         "brushing": "brush", "freezing": "freeze", "bending": "bend", "poking": "poke", "investigating":
         "investigate", "setting": "set", "moving": "move", "balancing": "balance", "swatting": "swat",
         "leaning": "lean", "rushing": "rush", "catching": "catch", "wiping": "wipe", "skipping": "skip"}
# Verbs whose sentences are captions ("climb ladder" -> "climbs ladder").
VERBS = set("""walk run jog jump hop leap climb hang swing drop sit stand get rise lie fall crawl pick scoop bend kick
punch throw catch toss pitch dance march sneak creep limp turn step wave bow stretch yawn squat kneel crouch roll
push pull carry drag lift sweep mop wash wipe clean paint dig plant rake chop saw hammer screw unscrew drink eat
sip chug shake answer dial type write fish row drive drum laugh cry argue flex peep duck skip bounce balance look
search wait shoot hold coil vacuum teach comb brush put open close mix shave slice sew swat lean move go navigate
follow avoid spin twist twirl pivot veer dribble shoot stumble trip slip dive grab reach lower descend dangle rock
smash threaten stare comfort shelter pass give join resist pull stride wander pace hobble shuffle tiptoe hurry rush
set place swim imitate investigate poke freeze scramble whistle play mime adjust fix overtake pound point explain
high-five""".split())
# Action nouns: "front kick" -> "does a front kick".
NOUNS = set("""kick jump walk run turn dance jete pirouette arabesque cartwheel cartwheels backflip backflips flip
flips handstand handstands somersault summersult spin spins twirl roll hop hops jumps kicks punches squats
stretches pushups jacks stroke sidestep step steps stride march swing swings putt bunt shot shoot pitch toss throw
lay-up layup dribble twists salute bow curtsey shrug stance pose signals moonwalk breakdance charleston lindyhop lambada
macarena salsa waltz tai chi yoga boxing swordplay stumble slip fall dive""".split())
# words -> what they mean as a whole phrase (checked before anything else).
PHRASES = {
    "boxing": "boxes", "tai chi": "does tai chi", "yoga": "does yoga", "swordplay": "fights with a sword",
    "swimming": "mimes swimming", "breast stroke": "mimes the breaststroke", "back stroke": "mimes the backstroke",
    "fly stroke": "mimes the butterfly stroke", "break stroke": "mimes the breaststroke",
    "free style": "mimes front crawl swimming", "butterfly": "mimes the butterfly stroke",
    "moonwalk": "does the moonwalk", "breakdance": "breakdances", "salsa dance": "dances salsa",
    "lambada dance": "dances the lambada", "macarena dance": "dances the macarena", "chicken dance": "does the chicken dance",
    "russian dance": "does a russian dance", "charleston": "dances the charleston", "lindy hop": "dances the lindy hop",
    "xtra fancy charleston": "dances the charleston", "fancy foot work": "does fancy footwork",
    "weight lifting": "lifts weights", "hand shake": "shakes hands", "high five": "gives a high five",
    "peek a boo": "plays peekaboo", "peekaboo": "plays peekaboo", "ring around the rosie": "plays ring around the rosie",
    "hopscotch": "plays hopscotch", "frisbee": "throws a frisbee", "idle": "stands idle", "standing": "stands still",
    "standing still": "stands still", "static pose": "holds a static pose", "thinker": "poses like the thinker",
    "robot": "moves like a robot", "zombie": "moves like a zombie", "childish": "moves in a childish way",
    "flamingo, lift legs high": "stands like a flamingo, lifting the legs high", "marching": "marches",
    "jumping jacks": "does jumping jacks", "putt": "putts a golf ball", "placing tee": "places a golf tee",
    "placing ball": "places a golf ball", "picking up ball": "picks up a ball", "baseball swing": "swings a baseball bat",
    "baseball bunt": "bunts a baseball", "baseball pitch": "pitches a baseball", "underhand fast pitch":
    "pitches a ball underhand", "underhand toss": "tosses a ball underhand", "basketball signals":
    "makes basketball referee signals", "soccer - kick ball": "kicks a soccer ball", "get up face down":
    "gets up from lying face down", "walk crawl": "crawls", "crawling": "crawls", "lay down": "lies down",
    "roll over": "rolls over", "fall on face": "falls on their face", "mawashigeri": "does a roundhouse kick",
    "yokogeri": "does a side kick", "oiduki": "does a lunge punch", "gedanbarai": "does a low block",
    "syutouuke": "does a knife-hand block", "front kick": "does a front kick", "kicking": "kicks",
    "punching": "punches", "throwing": "throws", "pacing": "paces back and forth", "waving": "waves",
    "wave hello": "waves hello", "wave": "waves", "bow": "bows", "curtsey": "curtseys", "shrug": "shrugs",
    "stretching": "stretches", "jump": "jumps", "run": "runs", "walk": "walks", "walking": "walks",
    "sneaking": "sneaks", "sneak": "sneaks", "sneaky": "sneaks", "looking around": "looks around",
    "run/jog": "runs", "walk/stride": "walks with long strides", "walk/wander": "wanders around", "walk/hobble": "hobbles",
    "slow walk/stride": "walks slowly with long strides", "climb 3 steps": "climbs three steps",
    "kickflip": "does a kick flip", "kick flip stumble": "does a kick flip and stumbles", "hand spring": "does a handspring",
    "bkwd summersult": "does a backward somersault", "bck flp twst fall": "does a back flip with a twist and falls",
    "side flip": "does a side flip", "front hand flip": "does a front handspring", "backflip": "does a backflip",
    "cartwheel": "does a cartwheel", "cartwheels": "does cartwheels", "hand stand kicks": "kicks in a handstand",
    "stretch and cartwheel": "stretches and does a cartwheel", "monkey backflip": "does a backflip",
    "banana peel slip": "slips as on a banana peel", "bannana peel slip": "slips as on a banana peel",
    "rug pull fall": "falls as if a rug were pulled away", "90 twists fall": "twists and falls",
    "get up from floor": "gets up from the floor", "get up from ground": "gets up from the ground",
    "get up from ground laying on back": "gets up from lying on the back",
    "get up laying on side": "gets up from lying on the side", "sitting on ground relaxing": "sits on the ground relaxing",
    "high sit": "sits down on a high seat", "medium sit": "sits down on a medium seat", "low sit": "sits down on a low seat",
    "sit on stool": "sits on a stool", "sitting in chair": "sits in a chair", "duck under": "ducks under something",
    "ducking": "ducks", "step over": "steps over something", "stepping over": "steps over something",
    "jump off ledge": "jumps off a ledge", "pump jump": "jumps", "2 foot jump": "jumps with both feet",
    "2 jump": "jumps twice", "180 degree jump": "jumps and turns 180 degrees in the air", "180 jump":
    "jumps and turns 180 degrees in the air", "360 jump": "jumps and turns a full circle in the air",
    "360 jumps": "jumps and turns full circles in the air", "high jump": "does a high jump",
    "jumping heights": "jumps up high", "jump distances": "jumps far", "jumping distances": "jumps far",
    "jumping sideways": "jumps sideways", "jumping twists": "jumps with twists", "jump stop": "jumps and stops",
    "singing in the rain jump": "jumps and clicks the heels", "punch/strike": "punches",
    "punch and kick": "punches and kicks", "punch kick": "punches and kicks", "jumps kicks and punches":
    "jumps, kicks and punches", "catch and throw": "catches and throws", "throw and catch": "throws and catches",
    "toss and catch": "tosses and catches", "catch and throw football": "catches and throws a football",
    "slap hands, throw it back": "slaps hands and throws it back", "lifting up": "lifts something up",
    "pick up": "picks something up", "picking up something": "picks something up",
    "run turn left": "runs and turns left", "run turn right": "runs and turns right", "run left": "runs to the left",
    "run right": "runs to the right", "run quick stop run": "runs, stops quickly and runs again",
    "run stop run": "runs, stops and runs again", "run jump stop run": "runs, jumps, stops and runs again",
    "run dive over roll run": "runs, dives over something, rolls and runs on", "run duck underneath":
    "runs and ducks under something", "run roll underneath": "runs and rolls under something",
    "run jump over": "runs and jumps over something", "run to quick stop": "runs and stops quickly",
    "run to stop": "runs and stops", "run to sneak": "runs, then sneaks", "run side step left":
    "runs and sidesteps to the left", "run side step right": "runs and sidesteps to the right",
    "start walk stop": "starts walking and stops", "start walk left": "starts walking to the left",
    "start walk right": "starts walking to the right", "start to run": "starts to run", "start run": "starts to run",
    "start jog": "starts to jog", "jog stop": "jogs and stops", "run stop": "runs and stops",
    "walk stop walk": "walks, stops and walks again", "walk to run": "walks, then runs", "walk jump": "walks and jumps",
    "jump turn": "jumps and turns", "small jump turn": "jumps and turns a little", "jump small forward":
    "does a small jump forward", "jump forward": "jumps forward", "start hop stop": "starts hopping and stops",
    "start duck underneath stop": "ducks under something", "stumble walk": "stumbles while walking",
    "walk evasive left": "walks and dodges to the left", "walk evasive right": "walks and dodges to the right",
    "walk duck footed": "walks duck-footed", "walk left": "walks to the left", "walk right": "walks to the right",
    "further jump turn": "jumps and turns further", "jump twist": "jumps and twists", "run jump": "runs and jumps",
    "lean turn left": "leans and turns left", "lean turn right": "leans and turns right",
    "push turn left": "pushes off and turns left", "push turn right": "pushes off and turns right",
    "walk slow": "walks slowly", "slow walk": "walks slowly", "walk fast": "walks fast", "quick walk": "walks quickly",
    "walk forward": "walks forward", "walk backwards": "walks backwards", "walking backwards": "walks backwards",
    "walk sideways": "walks sideways", "walk sideway": "walks sideways", "turn in place": "turns in place",
    "side twists": "twists to the sides", "bend over": "bends over", "hand stand kicks": "kicks in a handstand",
    "cat pick up": "picks something up like a cat", "pulling a gun": "pulls a gun",
}
# cryptic descriptions: the trial stays uncaptioned.
CRYPTIC = re.compile(r"^(clean(ed)?|story|lavish|cool|tv|cold|devil|airplane|helicopter|motorcycle( ?pose)?|"
                     r"superhero|genie|rushed|relaxed|upset|sexy|shy|happy|very happy|sad|elated|joy|depressed|"
                     r"scared|mope|clumsy|elderlyman|alaskan? vacation|sequesnce|long ?sequence ?good|"
                     r"up ?right ?sequence|slope ?\d+|digital ?8|forward|start|swing|go forward|"
                     r"bassai|empi|heiansyodan|around the world high five low|alien turn|[\d.\s]+(lbs?)?|"
                     r"mickey.*|ball mount|chip ?monk|animal|shifting weight|planting|hard days drink|"
                     r"painfulleftknee|end ?of ?break ?dance|break ?sequence ?with ?flips|spastic ?(stop|walk)|"
                     r"stop an[dg] go|run through|jog through|running ?no ?ball|running ?straight|"
                     r"smallforward|small ?forward|sraight ?drive ?from ?stop|.*drive \(.*\)|"
                     r"(defensive|offensive).*|(fake ?shot|feint).*|(left|right|super) ?(tight|wide)? ?(tight|wide) ?(turn|left|right)?|"
                     r"super ?tight ?(left|right)|running ?(tigher|tighter|wide) ?(left|right))$")
ANIMALS = set("""bear bird cat chicken cow dinosaur dog dragon elephant fish gorilla hippo horse hummingbird insect
monkey mouse panda panther penguin pterosaur quail roadrunner snake squirrel tiger whale t-rex tyrannosaurus
prairie chipmunk""".split())
CHARACTERS = {"cat": "a cat", "chicken": "a chicken", "dinosaur": "a dinosaur", "drunk": "a drunk",
              "gangly teen": "a gangly teenager", "graceful lady": "a graceful lady", "old man": "an old man",
              "sexy lady": "a sexy lady", "strong man": "a strong man"}
_CHARACTER_ACTS = {"walk": "walks like {}", "pick up": "picks something up like {}", "wait": "waits like {}",
                   "coffee mug": "drinks from a coffee mug like {}"}
CONTEXTS = {"playground": "on a playground", "basketball": "with a basketball", "football": "with a football",
            "acrobatics": "as acrobatics", "vignettes": "", "navigate": "", "conversation": "in a conversation",
            "quarrel": "in a quarrel", "violence": "", "stretch": "", "hand signals": "", "dance": "in a dance",
            "soccer": "with a soccer ball"}
SUBJECT = "a person"


@dataclass
class Action:
    phrase: str  # a verb phrase: "climbs a ladder"
    verb: str | None = None  # the checked verb a window must show for this phrase (mld_core.data.verbs)


@dataclass
class TrialPlan:
    skip: str | None = None  # why the trial is not prepared
    sentences: list[str] = field(default_factory=list)  # captions true of the whole trial
    actions: list[Action] = field(default_factory=list)  # the description's actions, in order
    kit: list[str] = field(default_factory=list)

    @property
    def several_actions(self) -> bool:
        return len({a.phrase for a in self.actions}) > 1


# --------------------------------------------------------------------------------------------------------------
# words


def normalise(description: str) -> str:
    """Lower case, CamelCase split, 'CleanedGRS' and trailing '_01' dropped, spaces collapsed."""
    text = re.sub(r"\s*Cleaned ?GR[Ss]\s*$", "", description.strip(), flags=re.I)
    text = re.sub(r"_\d+$", "", text)
    text = re.sub(r"(?<=[a-z])(?=[A-Z])|(?<=[A-Za-z])(?=\d)|(?<=\d)(?=[A-Za-z])", " ", text)
    text = re.sub(r"\s+", " ", text).strip().lower()
    text = re.sub(r" (digital |in |in a )?(figure )?(8|eight)$", " in a figure eight", text)
    return re.sub(r"(?<=[a-z]) \d+$", "", text)


def third_person(verb: str) -> str:
    if verb in _IRREGULAR:
        return _IRREGULAR[verb]
    if re.search(r"(s|sh|ch|x|z|o)$", verb):
        return verb + "es"
    if re.search(r"[^aeiou]y$", verb):
        return verb[:-1] + "ies"
    return verb + "s"


def base_verb(word: str) -> str | None:
    """The base verb a word stands for ("walking" -> "walk", "climbs" -> "climb"), or None."""
    if word in VERBS:
        return word
    if word in _BASE:
        return _BASE[word]
    if word.endswith("s") and word[:-1] in VERBS:
        return word[:-1]
    if word.endswith("es") and word[:-2] in VERBS:
        return word[:-2]
    if word.endswith("ing") and word[:-3] in VERBS:
        return word[:-3]
    return None


def verb_phrase(part: str) -> str | None:
    """One action of a description as a verb phrase ("climb ladder" -> "climbs a ladder"), None if not understood."""
    part = part.strip(" .;:")
    if not part:
        return None
    if part in PHRASES:
        return PHRASES[part]
    for name, article in CHARACTERS.items():
        for act, pattern in _CHARACTER_ACTS.items():
            if part == f"{name} {act}":
                return pattern.format(article)
    words = part.split()
    if words[0] in ANIMALS or part in ANIMALS:
        return f"moves like {_article(part)}"
    base = base_verb(words[0])
    if base is not None:
        rest = " ".join(words[1:])
        rest = re.sub(r"^((?:on|in|up|off|from|over|onto|into|to) )?(ladder|bar|box|object|stool|chair|stepstool|"
                      r"ledge|suitcase|floor|window|hole)\b", r"\1the \2", rest)
        return f"{third_person(base)} {rest}".strip()
    if words[-1] in NOUNS or (len(words) > 1 and words[-2] in NOUNS):
        noun = " ".join(words)
        return f"does {noun}" if words[-1].endswith("s") and words[-1] not in ("jacks",) else f"does {_article(noun)}"
    return None


def _article(noun: str) -> str:
    return ("an " if noun[0] in "aeiou" else "a ") + noun


def join_phrases(phrases: list[str]) -> str:
    unique = list(dict.fromkeys(phrases))
    return unique[0] if len(unique) == 1 else ", ".join(unique[:-1]) + " and " + unique[-1]


def split_actions(text: str) -> list[str]:
    """'climb, hang, swing, drop' -> its parts (commas, semicolons, ' and ', ' then ', '/' between verbs)."""
    parts = []
    for piece in re.split(r"\s*[;,/]\s*|\s+and\s+|\s+then\s+", text):
        if piece.strip():
            parts.append(piece.strip())
    return parts


# --------------------------------------------------------------------------------------------------------------
# a trial's plan


def subject_parts(text: str, letter: str) -> str | None:
    """A two-subject description's parts that say what subject ``letter`` does (parts led by another letter
    dropped; parts with no letter apply to both), with the letters replaced by people; None if nothing is left."""
    kept = []
    for clause in re.split(r"\s*;\s*", text):
        owner = "both"
        for part in re.split(r"\s*,\s*", clause):
            lead = re.match(r"^([ab])\s+(.*)$", part)
            if lead:
                owner, part = lead.group(1), lead.group(2)
            if owner in ("both", letter) and part:
                kept.append(part)
    other = "b" if letter == "a" else "a"
    out = ", ".join(kept)
    out = re.sub(rf"\b{other}'s\b", "the other person's", out)
    out = re.sub(rf"\b{other}\b", "the other person", out)
    out = re.sub(rf"\b{letter}\b", "themselves", out)
    return out or None


def trial_plan(description: str, kit: list[str] | None = None) -> TrialPlan:
    """What a trial's description and KIT sentences say: skip it, or its whole-trial captions and actions."""
    kit = list(kit or [])
    text = normalise(description)
    if SKIP.search(text):
        return TrialPlan(skip=f"a calibration, range-of-motion, T-pose or faulty take ({description!r})")
    two = _TWO_SUBJECTS.search(text)
    if two:
        text = subject_parts(text[: two.start()], two.group(1))
        if text is None:
            return TrialPlan(skip=f"two subjects; the description does not say what subject "
                                  f"{two.group(1).upper()} does ({description!r})")
    actions = _actions(text)
    sentences = [f"{SUBJECT} {join_phrases([a.phrase for a in actions])}"] if actions else []
    return TrialPlan(sentences=_with_context(sentences, text), actions=actions, kit=kit)


def _actions(text: str) -> list[Action]:
    if not text or CRYPTIC.match(text):
        return []
    human = _HUMAN_SUBJECT.search(text)
    if human:
        return [Action(f"imitates {_article(text[: human.start()])}")]
    context, sep, rest = text.partition(" - ")
    body = rest if sep and context in CONTEXTS else text
    parts = split_actions(body)
    understood = [(raw, p) for raw, p in ((raw, verb_phrase(raw)) for raw in parts) if p]
    whole = verb_phrase(body)
    if len(understood) >= 2:
        return [Action(p, _shown_verb(raw)) for raw, p in understood]
    if whole is not None:
        return [Action(whole, _shown_verb(body))]
    if understood:
        return [Action(understood[0][1], _shown_verb(understood[0][0]))]
    return [Action("dances")] if body is rest and context == "dance" else []


_WALK = re.compile(r"\b(walk\w*|march\w*|stroll\w*|strid\w+|pac(e|es|ing)|wander\w*)\b")
_RUN = re.compile(r"\b(run|runs|running|jog\w*|sprint\w*)\b")


def _shown_verb(text: str) -> str | None:
    """The verb a window must show for this action: a checked verb, else walk or run, else None (not locatable)."""
    from mld_core.data.verbs import verbs_in

    found = verbs_in(text)
    if found:
        return found[0]
    return "walk" if _WALK.search(text) else "run" if _RUN.search(text) else None


def _with_context(sentences: list[str], text: str) -> list[str]:
    context, sep, _ = text.partition(" - ")
    where = CONTEXTS.get(context, "") if sep else ""
    return [s if not where or (where == "in a dance" and "danc" in s) else f"{s} {where}" for s in sentences]


# --------------------------------------------------------------------------------------------------------------
# a window's captions


def window_captions(plan: TrialPlan, joints: np.ndarray, whole: bool) -> list[str]:
    """The captions of one window (T, 22, 3) of a trial: everything when the window is the whole trial or the
    description names one action; otherwise the named actions a detector finds in this window (none: uncaptioned)."""
    if whole:
        return plan.kit + plan.sentences
    if not plan.several_actions:
        return plan.kit + plan.sentences
    from mld_core.eval.physical import shows

    found = [a.phrase for a in plan.actions if a.verb is not None and shows(joints, a.verb)]
    return [f"{SUBJECT} {join_phrases(found)}"] if found else []
