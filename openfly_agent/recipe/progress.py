"""How far each training stage of a recipe run got against its step budget, and the header its table carries.

A stage trains a fixed number of steps (`StageBudget.steps`); its minutes are only a guard. When the guard stops a
stage first, the machine was slower than the one the budget was set on, and the run's figures are not those of
the recipe: the header printed above the tables says so, stage by stage.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from openfly_agent.eval.outputs import SUMMARY_MD
from openfly_agent.recipe.config import RecipeConfig
from openfly_agent.recipe.report import rl_comparison, rl_markdown
from openfly_agent.recipe.run import KIND_TRAIN, RL_DIR, recipe_steps
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.state import TrainerState


@dataclass
class StageProgress:
    """One training stage of a run: the steps its last checkpoint reached and the steps it was given."""

    name: str  # "grounding", "navigation", "dagger-r1-train", ...
    steps_done: int
    steps_planned: int
    minutes: float  # its guard

    @property
    def cut_short(self) -> bool:
        return self.steps_done < self.steps_planned

    def describe(self) -> str:
        """`navigation: 3,036 of 3,036 steps`, plus a warning when the guard stopped it first."""
        text = f"{self.name}: {self.steps_done:,} of {self.steps_planned:,} steps"
        if self.cut_short:
            text += (
                f" (its {self.minutes:g}-minute guard stopped it): this machine is slower than the reference; "
                "expect lower SR"
            )
        return text


def stage_progress(cfg: RecipeConfig) -> list[StageProgress]:
    """The training stages of `cfg` that have a checkpoint, in recipe order (read from trainer_state.json)."""
    budgets = {"grounding": cfg.grounding.minutes, "navigation": cfg.navigation.minutes, "rl": cfg.rl.minutes}
    progress = []
    for step in recipe_steps(cfg):
        if step.kind != KIND_TRAIN:
            continue
        latest = CheckpointManager(step.folder, keep_last=1).latest()
        if latest is None:  # not trained (yet)
            continue
        minutes = budgets.get(step.name, cfg.dagger.train.minutes)
        progress.append(StageProgress(step.name, TrainerState.load(latest).step, step.steps, minutes))
    return progress


def budget_header(progress: list[StageProgress]) -> str:
    """Markdown lines naming each stage's steps; the first line says whether every stage ran its budget."""
    if not progress:
        return ""
    short = [p for p in progress if p.cut_short]
    title = (
        f"**Cut short**: {len(short)} training stage(s) stopped at the time guard before their steps; "
        "these figures are not the recipe's."
        if short
        else "Every training stage ran its full number of steps."
    )
    return "\n".join([title, "", *(f"- {p.describe()}" for p in progress)]) + "\n"


def recipe_report(cfg: RecipeConfig) -> str:
    """The stages' header followed by every evaluation table the run wrote (eval/ and eval-<cities>/) and, after an
    RL stage, the paired difference of its agent from the agent it started from: what
    `python -m openfly_agent.recipe` prints at the end and writes to `<output_dir>/summary.md`."""
    out = Path(cfg.output_dir)
    parts = [f"# Recipe run {out}\n", budget_header(stage_progress(cfg))]
    for table in [out / "eval" / SUMMARY_MD, *sorted(out.glob(f"eval-*/{SUMMARY_MD}"))]:
        if table.is_file():
            parts.append(f"## {table.parent.name}\n\n{table.read_text().strip()}\n")
    comparison = rl_comparison(out) if cfg.rl.steps else None
    if comparison is not None:
        parts.append(f"## {RL_DIR}\n\n{rl_markdown(comparison).strip()}\n")
    return "\n".join(parts)
