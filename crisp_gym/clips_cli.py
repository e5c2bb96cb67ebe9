"""``crisp clips``: list the registered clips (bundled and the user's)."""

from __future__ import annotations

from crisp_gym.registry import list_clips, user_registry_path


def main(argv: list[str] | None = None) -> int:
    if argv:
        print("usage: crisp clips   (lists the registered clips; takes no arguments)")
        return 0 if argv[0] in ("-h", "--help") else 2
    clips = list_clips()
    width = max((len(n) for n in clips), default=4)
    for name, entry in sorted(clips.items()):
        state = "" if entry["path"].is_dir() else "  (missing)"
        print(f"{name:<{width}}  {', '.join(entry['tags']):<28} {entry['path']}{state}")
    print(f"\nuser registry: {user_registry_path()}")
    return 0
