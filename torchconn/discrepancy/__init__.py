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

from ..physics.effects import (
    REGISTRY,
    AmbientFlow,
    BodyDrift,
    DragRatio,
    Effect,
    JointBias,
    LinkLength,
    MarkerOffset,
    Param,
    TimeLag,
    get_effect,
    register,
)
from .confounding import principal_cosine, separating_experiments, signature_collinearity
from .forward import ForwardModel, Measurement, prepare_measurement
from .model import AugmentedModel, load_augmented
from .report import VERDICTS, DiscrepancyReport
from .residuals import compare_terms, phase_profile
from .simulate import effect_parameters, simulate_with_effects
from .workflow import DiscrepancySettings, diagnose

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
