"""Configuration: the one YAML loader, recipes and rig profiles.

* :mod:`rig.config.loader`: YAML with a file and line for every node (duplicate keys,
  depth and size rejected, ``extends`` overlays), strict validation, :class:`ConfigError`
  naming file, field and line; :func:`load_model_yaml` for model files.
* :mod:`rig.config.profile`: :class:`RigProfile` (plant, controller, sensors, lubricants,
  typed ``hardware`` section), :func:`load_profile`.
* :mod:`rig.config.recipe`: :class:`Recipe`, :func:`load_recipe`, :func:`compile_recipe`
  (recipe -> :class:`trajectories.PlanSpec` -> :class:`trajectories.Plan`).
"""

from rig.config.loader import ConfigError, StrictModel, load_model_yaml
from rig.config.profile import ProfileError, RigProfile, default_profile_path, load_profile
from rig.config.recipe import LUBRICANTS, Recipe, RecipeError, compile_recipe, load_recipe, parse_recipe

__all__ = ["ConfigError", "StrictModel", "load_model_yaml", "ProfileError", "RigProfile", "default_profile_path",
           "load_profile", "LUBRICANTS", "Recipe", "RecipeError", "compile_recipe", "load_recipe", "parse_recipe"]
