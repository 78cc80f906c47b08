"""The dry builds of the published studies (``BUILD_CHECKS`` of :mod:`experiments.schemas`): what a study
builds from its config before its first unit - its estimators on its scenario(s), its sensor system - built
by the precheck (:func:`experiments.config.dry_build`) in the run's dtype on the CPU, before any folder
exists. A constructor's refusal is one :class:`~experiments.checks.ConfigError` naming the key
(:func:`~experiments.checks.build_error`: the node's key the constructor names, else the node). Nothing
is simulated or filtered. Each function is ``check(cfg, scenario)``: ``cfg`` the resolved config,
``scenario`` the built ``scenario`` node (None for a study without one).
"""

from __future__ import annotations

import torch
from hydra.utils import instantiate

from experiments.checks import ConfigError, build_error

#: the single-filter builder (the smoothing study sets its ``mode`` from ``smoothing.cv_mode``)
SINGLE = "experiments.estimators.kalman"


def _dtype(cfg) -> torch.dtype:
    return {"float32": torch.float32, "float": torch.float32}.get(str(cfg.get("dtype")), torch.float64)


def _built(key: str, node, make, aliases: dict | None = None):
    """``make()``, its error as one line naming ``key`` (or the key of ``node`` it names)."""
    try:
        return make()
    except ConfigError:
        raise
    except Exception as err:  # noqa: BLE001 - any constructor's refusal, named by its key
        raise build_error(key, node, err, aliases) from None


def _estimators(nodes, scenario, prefix: str = "estimators", options=None) -> dict:
    """Every ``nodes[name]`` (a partial builder of experiments/estimators.py) called on ``scenario``;
    ``options(node)``: the study's own keywords for a node. The estimators by name."""
    built = {}
    for name in nodes:
        node = nodes[name]
        extra = options(node) if options is not None else {}
        built[name] = _built(f"{prefix}.{name}", node,
                             lambda: instantiate(node)(scenario, name=str(name), **extra))
    return built


def _scenario(cfg, node, key: str):
    return _built(key, node, lambda: instantiate(node, dtype=_dtype(cfg), device="cpu"))


def imm_baseline(cfg, scenario) -> None:
    """imm_baseline and quickstart: every estimator on the scenario."""
    if scenario is not None:
        _estimators(cfg.estimators, scenario)


def smoothing(cfg, scenario) -> None:
    """Every estimator on each of ``smoothing.scenarios``, a single filter on that scenario's
    ``smoothing.cv_mode``; each one a filter ``torchmm.smooth`` has a smoother for (the study smooths them
    all: ``why_not_smoothable``)."""
    from torchmm.smooth_checks import why_not_smoothable

    for key in cfg.smoothing.scenarios:
        built = _scenario(cfg, cfg.smoothing.scenarios[key], f"smoothing.scenarios.{key}")
        mode = int(cfg.smoothing.cv_mode[key])
        estimators = _estimators(cfg.estimators, built,
                                 options=lambda node: {"mode": mode} if node.get("_target_") == SINGLE else {})
        for name, est in estimators.items():
            why = why_not_smoothable(est.filter)
            if why is not None:
                raise ConfigError(f"estimators.{name}", cfg.estimators[name].get("_target_"),
                                  f"the smoothing study smooths every estimator: {why}")


def imm_analysis(cfg, scenario) -> None:
    """Every estimator on both scenarios of ``analysis.scenarios``, with the first alpha's transition."""
    from torchmm import alpha_transition

    for key in cfg.analysis.scenarios:
        built = _scenario(cfg, cfg.analysis.scenarios[key], f"analysis.scenarios.{key}")
        alphas = list(cfg.analysis.alphas[key])
        if not alphas:
            continue
        matrix = alpha_transition(torch.full((built.num_modes,), float(alphas[0]), dtype=_dtype(cfg)))
        _estimators(cfg.estimators, built, options=lambda node: {"transition": matrix})


def imm_tf(cfg, scenario) -> None:
    """Every estimator of ``estimator_names`` (``tf_estimators``) on the scenario and the source sensor."""
    from experiments.studies.imm_tf import build_estimators

    if scenario is None:
        return
    for name in cfg.estimator_names:
        _built(f"tf_estimators.{name}", cfg.tf_estimators[name],
               lambda: build_estimators(scenario, float(cfg.source.R), cfg, [name]))


def gimmaf(cfg, scenario) -> None:
    """The estimators of ``gimmaf.estimators`` (their models: ``model_rates``, ``transition``,
    ``nominal_q``)."""
    from experiments.studies.gimmaf import build_estimators

    g = cfg.gimmaf
    _built("gimmaf", g, lambda: build_estimators(g, float(g.noise.R), float(g.noise.delta), float(g.noise.nu),
                                                 dtype=_dtype(cfg), device="cpu"))


#: the fusion studies' library arguments -> their config keys
RADAR_KEYS = {"Q_eta": "eta_std", "Qw": "Qw_diag", "mu0": "x0", "P0": "P0_diag", "h": "h_factor",
              "Qp": "sigma_r"}
UPS_KEYS = {"P0": "P0_scale"}


def fusion_radar(cfg, scenario) -> None:
    """The radar system (56)-(58) from ``radar``."""
    from experiments.studies.fusion_radar import radar_system

    _built("radar", cfg.radar, lambda: radar_system(cfg.radar, _dtype(cfg), "cpu"), RADAR_KEYS)


def fusion_ups(cfg, scenario) -> None:
    """The UPS system from ``ups``."""
    from experiments.studies.fusion_ups import ups_system

    _built("ups", cfg.ups, lambda: ups_system(cfg.ups, _dtype(cfg), "cpu"), UPS_KEYS)


def learn_dynamics(cfg, scenario) -> None:
    """The study's turning scenario from ``learn.scenario``."""
    from experiments.studies.learn_dynamics import turning_scenario

    node = cfg.learn.scenario
    _built("learn.scenario", node, lambda: turning_scenario(node, _dtype(cfg), "cpu"))


def mevsmm(cfg, scenario) -> None:
    """Every estimator of ``mevsmm.estimator_names`` (all of ``mevsmm.estimators`` when null) on the
    scenario."""
    from experiments.studies.mevsmm import STUDY_KEYS

    if scenario is None:
        return
    nodes = cfg.mevsmm.estimators
    for name in cfg.mevsmm.get("estimator_names") or list(nodes):
        node = {k: v for k, v in nodes[name].items() if k not in STUDY_KEYS}
        _built(f"mevsmm.estimators.{name}", nodes[name], lambda: instantiate(node)(scenario))
