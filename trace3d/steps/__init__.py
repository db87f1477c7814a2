"""The ``trace3d`` commands: the step registry (:mod:`.registry`, re-exported here) and one handler module
per command, ``trace3d/steps/<command>.py`` with its ``run(args)`` (``-`` written ``_``).

Importing this package is cheap: the registry imports nothing of the library, and a handler's module is
loaded by name only when its command runs (:func:`handler`).
"""

from __future__ import annotations

from .registry import (BY_COMMAND, BY_RULE, FITTED_MASK_SOURCES, GROUND_TRUTH, IMPORTERS, LIFT_METHODS, PACKAGE,
                       PARAMS_HELP, SCENE_KINDS, SIMULATE_PARAMS, STEPS, Arg, Step, Variant, arg, default_inconsistency,
                       fields_static, handler, lift_keys, lift_params_for, load_class, params_arg, step,
                       variant_defaults)

__all__ = ["BY_COMMAND", "BY_RULE", "FITTED_MASK_SOURCES", "GROUND_TRUTH", "IMPORTERS", "LIFT_METHODS", "PACKAGE",
           "PARAMS_HELP", "SCENE_KINDS", "SIMULATE_PARAMS", "STEPS", "Arg", "Step", "Variant", "arg",
           "default_inconsistency", "fields_static", "handler", "lift_keys", "lift_params_for", "load_class",
           "params_arg", "step", "variant_defaults"]
