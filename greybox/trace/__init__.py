"""Trace a model error to the state equation(s) it enters, and describe it.

For one candidate error channel (a matrix G: which state equations, with
which weights) the unknown-input filter :func:`greybox.uikf` estimates the
model error d^ on estimation data. d^ is then explained

* **statically** (order 0): ``d[j] = f(x[j], u[j])``, a sparse law chosen by
  forward selection with a BIC stopping rule over named linear terms (states
  and inputs) and, optionally, the nonlinear terms ``x^3``, ``sign(x)``
  (a smooth ``tanh(x/eps)``) and ``|x|`` of every state (PAPER_NOTES §9.4);
* **dynamically** (order 1..max_order): the subsystem (19)-(20) with
  feedthrough, by :func:`greybox.identify_subsystem` (closed-loop subspace
  identification, PAPER_NOTES §8.4).

Both are kept (PAPER_NOTES §9.2): the workflow chooses between them by the
simulation error of the augmented model. Linear static laws and sparse
first-order dynamic laws of a continuous model are parametrized in
continuous time and refined by output error (``oe``, ``dynamic``); with
several effects, ``joint`` refits them all at once. Nonlinear laws stay in
discrete time: ``d[j]`` acts through the ZOH-discretized G between samples
j and j+1; one whose simulation is far above the noise model's floor and
whose d^ fit the simulation contradicts is refitted by output error and
pruned (``oe._refine_nonlinear_oe``). The one-step predictions of a model
with a nonlinear law come from an extended Kalman filter
(:func:`ekf_predict_with_law`).
"""


from .channel_trace import ChannelTrace, trace_channel
from .channels import (
    Channel,
    channel_model,
    default_channels,
    output_channel,
    resolve_channel_spec,
)
from .laws import (
    StaticLaw,
    aligned,
    ekf_predict_with_law,
    law_terms,
    output_terms,
    parameter_notes,
    predict_with_law,
    simulate_with_law,
)


__all__ = [
    "Channel",
    "default_channels",
    "output_channel",
    "resolve_channel_spec",
    "channel_model",
    "StaticLaw",
    "ChannelTrace",
    "trace_channel",
    "law_terms",
    "output_terms",
    "aligned",
    "simulate_with_law",
    "predict_with_law",
    "ekf_predict_with_law",
    "parameter_notes",
]
