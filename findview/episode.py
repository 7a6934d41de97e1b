"""The episode record shared by the dataset, the task, the agents and the metrics."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

DIFFICULTIES = ("easy", "medium", "hard")


@dataclass(frozen=True)
class Episode:
    """One FindView episode: find ``(target_pitch, target_yaw)`` starting from ``(init_pitch, init_yaw)``.

    Angles are integer degrees (pitch in ``[-60, 60]``, yaw in ``(-180, 180]``). ``image`` is the
    panorama path (absolute, or relative to the dataset root recorded in the episode file), ``label``
    its sub-category. ``seed`` drives everything random about the episode (e.g. target corruption).
    """

    episode_id: str
    image: str
    init_pitch: int
    init_yaw: int
    target_pitch: int
    target_yaw: int
    difficulty: str = "easy"
    label: str = ""
    seed: int = 0
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if not d["extra"]:
            d.pop("extra")
        return d

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "Episode":
        required = ("episode_id", "image", "init_pitch", "init_yaw", "target_pitch", "target_yaw")
        missing = [k for k in required if k not in d]
        if missing:
            raise ValueError(f"episode record is missing keys {missing}: {d}")
        return Episode(
            episode_id=str(d["episode_id"]),
            image=str(d["image"]),
            init_pitch=int(d["init_pitch"]),
            init_yaw=int(d["init_yaw"]),
            target_pitch=int(d["target_pitch"]),
            target_yaw=int(d["target_yaw"]),
            difficulty=str(d.get("difficulty", "easy")),
            label=str(d.get("label", "")),
            seed=int(d.get("seed", 0)),
            extra=dict(d.get("extra", {})),
        )
