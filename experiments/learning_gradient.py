"""The ``learn`` block's ``method: gradient`` of the generic study (split from :mod:`experiments.learning` and the
compare study by concern, issue 47; ``mle`` is :mod:`experiments.learning`'s, ``em``
:mod:`experiments.learning_em`'s): the named noise covariances made learnable
(:func:`torchmm.learnable_noise`) and fitted through one estimator with a torch optimiser."""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from experiments.config import ConfigError
from experiments.learning import GRADIENT_KINDS
from torchmm import run_filter

__all__ = ["fit_gradient", "gradient_targets"]


def gradient_targets(scenario, block, module_of) -> list:
    """``[(key, module, name, initial)]``: the named covariances of ``learn.parameters`` made learnable
    on ``scenario``'s models (:func:`torchmm.learnable_noise`). ``ConfigError`` naming the entry."""
    from torchmm import learnable_noise

    targets = []
    for i, p in enumerate(block.parameters):
        key = f"learn.parameters[{i}]"
        try:
            module = module_of(scenario, str(p.model))
        except ValueError as err:
            raise ConfigError(f"{key}.model", str(p.model), str(err)) from None
        name = str(p.name)
        value = getattr(module, name, None)
        if name not in ("Q", "R"):
            raise ConfigError(f"{key}.name", name, "method gradient learns the noise covariances Q (of a mode) and R "
                              "(of a sensor); method mle estimates any tensor")
        if not isinstance(value, Tensor):
            known = [n for n in ("Q", "R") if isinstance(getattr(module, n, None), Tensor)]
            raise ConfigError(f"{key}.name", name, f"{p.model} ({type(module).__name__}) has no covariance {name!r}"
                              + (f" (it has {', '.join(known)})" if known else ""))
        initial = value.detach().clone()
        kind = str(p.get("kind") or "log_diagonal")
        if kind not in GRADIENT_KINDS:
            raise ConfigError(f"{key}.kind", kind, f"method gradient takes {', '.join(GRADIENT_KINDS)}")
        try:
            learnable_noise(module, name, kind)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{key}", f"{p.model}.{name}", str(err)) from None
        targets.append((f"{p.model}.{name}", module, name, initial))
    return targets


def fit_gradient(scenario, block, build, module_of, z: Tensor, prior, *, name: str, burn: int, update_first: bool,
                 progress, controls: Tensor | None = None) -> dict:
    """``method: gradient``: the named covariances made learnable on ``scenario``'s models
    (:func:`gradient_targets`, ``module_of(scenario, model)`` naming a model), the estimator ``build()`` on
    them, and its filter fitted with a torch optimiser through :class:`torchmm.learn.Trainer`: the study's
    ``learned`` record (rows, the NLL over the iteration, the time)."""
    from torch.nn.utils import parametrize

    from torchmm.learn import Trainer

    targets = gradient_targets(scenario, block, module_of)
    est = build()
    params = [p for p in est.filter.parameters() if p.requires_grad]
    if not params:
        raise ValueError(f"learn.estimators: {name} has no learnable parameter (its filter does not use the "
                         "models of learn.parameters)")
    if str(block.optimizer) == "lbfgs":
        optimizer = torch.optim.LBFGS(params, lr=float(block.lr), max_iter=20, line_search_fn="strong_wolfe",
                                      tolerance_grad=1e-10, tolerance_change=1e-14)
    else:
        optimizer = torch.optim.Adam(params, lr=float(block.lr))

    def loss_fn(filter, belief0, measurements, controls=None, return_final=False):
        # belief0 is the estimator's start belief (Trainer.fit takes it as it is: no second conversion)
        traj = run_filter(filter, belief0, measurements, update_first=update_first, controls=controls,
                          record=lambda o: o._replace(belief=None, prior=None, innovation=None,
                                                      innovation_cov=None, extras={}))
        loss = -traj.log_likelihood[burn:].sum(0).mean()
        return (loss, None) if return_final else loss

    tol = float(block.get("tolerance") or 0.0)

    def converged(trainer, record) -> bool:  # the loss no longer moves (relative change below `tolerance`)
        h = trainer.history
        return len(h) > 1 and abs(h[-1].loss - h[-2].loss) <= tol * max(abs(h[-1].loss), 1.0)

    trainer = Trainer(est.filter, optimizer, loss_fn=loss_fn, callbacks=[converged] if tol > 0 else [])
    tic = time.perf_counter()
    history = trainer.fit(est.init(prior, None), z, int(block.iterations), controls=controls, progress=progress)
    seconds = time.perf_counter() - tic
    nll = [float(r.loss) for r in history]
    with parametrize.cached():
        learned = {key: getattr(module, name).detach().clone() for key, module, name, _ in targets}
    rows = []
    for key, _, _, _ in targets:
        value = learned[key].cpu()
        for flat, v in enumerate(value.reshape(-1).tolist()):
            index = np.unravel_index(flat, tuple(value.shape)) if value.dim() else ()
            rows.append([name, f"{key}[{','.join(str(int(i)) for i in index)}]", v, None, None])
    for _, module, name, _ in targets:  # freeze: the estimator runs with the learned values
        parametrize.remove_parametrizations(module, name, leave_parametrized=True)
        getattr(module, name).requires_grad_(False)
    return {"rows": rows, "nll": nll, "through": name, "seconds": seconds, "iterations": len(history),
            "method": "gradient", "optimizer": str(block.optimizer)}
