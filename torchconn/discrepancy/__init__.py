"""Stage 6 -- the discrepancy workflow: where simulation and measurement disagree, and why.

After a model is fitted, the simulator says one thing and the motion-capture data another. This
subpackage finds where they disagree, names the missing physical effect, adds it to the model and
shows the gap shrink::

    from . import diagnose
    report = diagnose(traj, NLinkSwimmer(3))
    print(report.summary())
    report.save("out/")            # report.json, augmented_model.json, figures

or from the shell: ``torchconn-discrepancy DATA.csv --links 3 --out out/``.

Modules, one per step: :mod:`torchconn.physics.effects` (the registry of named physical
effects, shared with the known conditions of :mod:`torchconn.known`),
:mod:`.simulate` (rollouts with effects on), :mod:`.forward` (the differentiable forward model
and the measurement it compares with), :mod:`.residuals` (residual profiles, the term-by-term
comparison), :mod:`.fitting` (autograd fits, cross-validation over cycles),
:mod:`.confounding` (collinearity, separating experiments), :mod:`.workflow` (:func:`diagnose`,
its named stages), :mod:`.report` (the stages' typed results and the report),
:mod:`.model` (the augmented model), :mod:`.figures`.
"""

from .._lazy import lazy_exports

#: the public names and the modules that define them, imported on first use (the workflow
#: loads scipy.stats, the report matplotlib: ``import torchconn.discrepancy`` loads neither)
_EXPORTS = {
    "Effect": "..physics.effects", "Param": "..physics.effects", "REGISTRY": "..physics.effects",
    "register": "..physics.effects", "get_effect": "..physics.effects",
    "AmbientFlow": "..physics.effects", "DragRatio": "..physics.effects",
    "MarkerOffset": "..physics.effects", "JointBias": "..physics.effects",
    "TimeLag": "..physics.effects", "LinkLength": "..physics.effects",
    "BodyDrift": "..physics.effects",
    "simulate_with_effects": ".simulate", "effect_parameters": ".simulate",
    "Measurement": ".forward", "ForwardModel": ".forward", "prepare_measurement": ".forward",
    "phase_profile": ".residuals", "compare_terms": ".residuals",
    "signature_collinearity": ".confounding", "principal_cosine": ".confounding",
    "separating_experiments": ".confounding",
    "diagnose": ".workflow", "DiscrepancySettings": ".workflow",
    "DiscrepancyReport": ".report", "VERDICTS": ".report",
    "AugmentedModel": ".model", "load_augmented": ".model",
}


__all__ = [
    "Effect", "Param", "REGISTRY", "register", "get_effect",
    "AmbientFlow", "DragRatio", "MarkerOffset", "JointBias", "TimeLag", "LinkLength", "BodyDrift",
    "simulate_with_effects", "effect_parameters",
    "Measurement", "ForwardModel", "prepare_measurement",
    "phase_profile", "compare_terms",
    "signature_collinearity", "principal_cosine", "separating_experiments",
    "diagnose", "DiscrepancySettings", "DiscrepancyReport", "VERDICTS",
    "AugmentedModel", "load_augmented",
]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
