"""benchmarks/recipe_time.py: its stages are the robust cards' "Make it" commands (FoV 90 and 60), and one run is
timed on the trainer ``tools/train.py`` builds for the preset."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "tools"))
import check_docs  # noqa: E402  (tools/check_docs.py: the docs test's command parser)
import recipe_time  # noqa: E402  (benchmarks/recipe_time.py)

from _training import blob_panorama  # noqa: E402

CARDS = {  # each recipe's model card heading in pretrained/README.md
    "fov90": "# `findview_sun360mini_indoor_robust.pth`",
    "fov60": "# `findview_sun360mini_indoor_robust_fov60.pth`",
}
# the overrides that set where a run reads and writes, or how many threads and validations it has: not the recipe
NOT_RECIPE = re.compile(r"(init_from|dataset(\.\w+)?|hydra\.[\w.]+|trainer\.torch_threads|trainer\.val_interval)=")


def card_train_commands(recipe: str) -> list[tuple[list[str], bool]]:
    """The ``tools/train.py`` commands in the "Make it" block of ``recipe``'s card, in order: (the recipe's
    overrides, whether it runs in the background with ``&``)."""
    text = (REPO / "pretrained" / "README.md").read_text()
    card = text[text.index(CARDS[recipe]):]
    make_it = card[card.index("## Make it"):]
    first_block = make_it[:make_it.index("```", make_it.index("```") + 3) + 3]  # up to its first block's end
    joined = " ".join(first_block.replace("\\\n", " ").split())  # as check_docs writes a command, then what follows
    commands = []
    for c in check_docs.extract(first_block):  # continuations joined, comments dropped, split at `&`
        words = c.text.split()
        if words[:2] == ["python", "tools/train.py"]:
            commands.append(([w for w in words[2:] if not NOT_RECIPE.match(w)], f"{c.text} &" in joined))
    return commands


@pytest.mark.parametrize("recipe, count", [("fov90", 5), ("fov60", 3)])
def test_the_stages_are_the_cards_commands(recipe: str, count: int):
    commands = card_train_commands(recipe)
    assert len(commands) == count, commands  # FoV 90: stage 1, stage 2, stage 3's pair, stage 4; FoV 60: 3 stages
    runs = [(list(run), len(stage.runs) > 1) for stage in recipe_time.RECIPES[recipe] for run in stage.runs]
    assert [(sorted(r), bg) for r, bg in runs] == [(sorted(c), bg) for c, bg in commands]


def test_one_run_is_timed_on_the_presets_trainer(tmp_path: Path, one_torch_thread):
    import cv2

    root = tmp_path / "panoramas"
    root.mkdir()
    for i in range(4):
        cv2.imwrite(str(root / f"pano_{i}.png"), blob_panorama(200 + i))
    data = ["dataset=folder", f"dataset.root={root}", f"dataset.out_dir={tmp_path / 'data'}", "dataset.name=recipe",
            "sim.prefetch_workers=0", "trainer.num_envs=2", "trainer.progress=false"]
    result = recipe_time.time_run(["+experiment=robust_wide", *data], updates=1, warmup=1)
    assert result["num_updates"] == 500  # configs/experiment/robust_polish.yaml, which robust_wide extends
    assert 0 < result["s_per_update"] < 60


def test_bad_sample_sizes_are_refused(capsys):
    with pytest.raises(SystemExit) as err:
        recipe_time.main(["--updates", "0"])
    assert err.value.code == 2
    assert "--updates and --warmup must be >= 1" in capsys.readouterr().err

