"""The navigation recipe as one resumable command: data -> grounding stage -> navigation stage -> DAgger rounds ->
RL stage (off by default) -> closed-loop evaluation with every baseline (docs/TRAINING.md, "Stages and the recipe")."""

from openfly_agent.recipe.config import DaggerSettings, EvalSettings, RecipeConfig, StageBudget
from openfly_agent.recipe.run import recipe_steps, run_recipe

__all__ = ["DaggerSettings", "EvalSettings", "RecipeConfig", "StageBudget", "recipe_steps", "run_recipe"]
