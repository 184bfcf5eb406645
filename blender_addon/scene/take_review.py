"""Preview, then Accept or Reject (bpy, main thread): new takes made in preview play on the armature, marked as
pending; Accept keeps them as ordinary takes, Reject deletes them and gives the armature back the Action it had."""

from __future__ import annotations

from .write_action import assign_action

PENDING = "mld_pending_actions"  # custom properties on the armature object
PREVIOUS = "mld_previous_action"


def mark_pending(obj, actions: list[str], previous: str) -> None:
    """Remember ``actions`` (just made on ``obj``) as pending, and the Action ``obj`` had before ('' none). A second
    preview before a decision rejects the first."""
    if PENDING in obj:
        previous = str(obj.get(PREVIOUS, ""))
        ad = obj.animation_data
        new = ad.action if ad is not None and ad.action is not None and ad.action.name in actions else None
        reject(obj)
        if new is not None:  # the rejection gave the armature its old Action back: the new take plays instead
            assign_action(obj, new)
    obj[PENDING] = ",".join(actions)
    obj[PREVIOUS] = previous


def pending(obj) -> list[str]:
    return [a for a in str(obj.get(PENDING, "")).split(",") if a] if obj is not None else []


def accept(obj) -> str:
    """Keep the pending takes; returns a message."""
    names = pending(obj)
    _clear(obj)
    return f"Kept {', '.join(names)}" if names else "Nothing to accept"


def reject(obj) -> str:
    """Delete the pending takes (their Actions and NLA strips) and assign the previous Action again."""
    import bpy

    names = pending(obj)
    previous = bpy.data.actions.get(str(obj.get(PREVIOUS, "")))
    ad = obj.animation_data
    if ad is not None:
        for track in list(ad.nla_tracks):
            if any(s.action is not None and s.action.name in names for s in track.strips):
                ad.nla_tracks.remove(track)
        assign_action(obj, previous)
    for name in names:
        action = bpy.data.actions.get(name)
        if action is not None:
            bpy.data.actions.remove(action)
    _clear(obj)
    return f"Removed {', '.join(names)}" if names else "Nothing to reject"


def _clear(obj) -> None:
    for key in (PENDING, PREVIOUS):
        if key in obj:
            del obj[key]
