"""The differentiable RCBF safety layer of SAC-RCBF (paper, "Differentiable Safety Layer").

u*(x, u_RL) = u_RL + u_S(x, u_RL), with u_S from the RCBF-QP assembled by the same
:meth:`RCBFProblem.qp` the per-step filter uses, solved for a whole minibatch in one call of
:func:`rcbf_ros.core.diffqp.solve_qp_batch` and differentiated through its KKT conditions, so the
actor and critic losses see the safe action (eqs. q_update_diff, pi_update_diff).
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from rcbf_ros.core.diffqp import solve_qp_batch
from rcbf_ros.core.lie_closed_form_batch import BatchClosedForm
from rcbf_ros.core.rcbf import RCBFProblem

DisturbanceModel = Callable[[Tensor], tuple[Tensor, Tensor]]
"""state (B, n_x) -> (mean (B, n_x), std (B, n_x)) of the disturbance estimate."""


class DifferentiableSafetyLayer:
    """Callable ``(state: (B, n_x), u_rl: (B, n_u)) -> u_safe: (B, n_u)``, differentiable in u_rl.

    The QP runs in float64 (accuracy of the KKT solve); the output is cast back to u_rl's dtype.
    """

    def __init__(self, problem: RCBFProblem, disturbance: DisturbanceModel | None = None) -> None:
        """Args:
            problem: system, barriers, gains (the same object the filter uses).
            disturbance: the learned estimate at a batch of states (None: no disturbance).
        """
        self.problem = problem
        self.disturbance = disturbance
        # The barrier terms are constants of the QP (the states are data): in closed form for
        # the built-in systems and barriers, else by autograd (RCBFProblem.terms).
        self._closed_form = BatchClosedForm.from_problem(problem)
        system = problem.system
        self._limits = ((torch.as_tensor(system.u_min, dtype=torch.float64),
                         torch.as_tensor(system.u_max, dtype=torch.float64))
                        if problem.has_limits else None)

    def correction(self, state: Tensor, u_rl: Tensor,
                   disturbance: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """u_S: (B, n_u).

        ``disturbance``: the estimate's (mean, std) at ``state``, each (B, n_x), when the caller
        has it already (the learner memoises it per stored transition); None asks the model.

        As in the per-step filter, a proposal outside the actuator limits is clipped before the
        QP (u_S then includes the clipping; its gradient there is zero). SAC's squashed policy
        proposes within its box, so training never meets the clip."""
        x = state.detach().to(torch.float64)
        u_in = u_rl.to(torch.float64)
        system = self.problem.system
        u = u_in if self._limits is None else torch.clamp(u_in, *self._limits)
        mean = std = None
        if disturbance is None and self.disturbance is not None:
            with torch.no_grad():
                disturbance = self.disturbance(x)
        if disturbance is not None:
            mean, std = (part.detach().to(torch.float64) for part in disturbance)
        terms = None if self._closed_form is None else self._closed_form.terms(x, u)
        qp = self.problem.qp(x, u, mean, std, terms=terms)
        z = solve_qp_batch(*qp)
        return (u - u_in + z[:, :system.n_u]).to(u_rl.dtype)

    def __call__(self, state: Tensor, u_rl: Tensor,
                 disturbance: tuple[Tensor, Tensor] | None = None) -> Tensor:
        return u_rl + self.correction(state, u_rl, disturbance)
