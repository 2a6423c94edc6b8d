"""action_decoder: DDPM, flow-matching and MeanFlow action decoders with marginal-preserving
SDE samplers, for vision-language-action robot policies.

Time convention (the whole library): t = 0 is the Gaussian prior, t = 1 is data.
"""

try:
    import torch as _torch  # noqa: F401
except ImportError:     # `action_decoder.runtime` (onnxruntime + NumPy) runs an exported policy without PyTorch
    _torch = None

if _torch is not None:
    from .config import DecoderConfig
    from .policy import ActionDecoderPolicy, PolicyOutput
    from .flows import (ChurnSigma, ExploringSigma, FixedSigma, LearnableSigma, SDEResult,
                        chain_log_prob, ddpm_loss, flow_matching_loss, make_sigma, meanflow_loss,
                        meanflow_target, sample_ddpm, sample_meanflow, sample_ode, sample_sde,
                        time_grid, velocity_from_meanflow, velocity_from_sample, rtc_weights,
                        sample_ode_rtc, sample_meanflow_rtc, sample_sde_rtc, sample_ode_prefix,
                        sample_meanflow_prefix)

__version__ = "0.1.0"

__all__ = ["ActionDecoderPolicy", "PolicyOutput", "ChurnSigma", "DecoderConfig", "ExploringSigma", "FixedSigma", "LearnableSigma",
           "SDEResult", "chain_log_prob", "ddpm_loss", "flow_matching_loss", "make_sigma",
           "meanflow_loss", "meanflow_target", "sample_ddpm", "sample_meanflow", "sample_ode",
           "sample_sde", "time_grid", "velocity_from_meanflow", "velocity_from_sample",
           "rtc_weights", "sample_ode_rtc", "sample_meanflow_rtc", "sample_sde_rtc", "sample_ode_prefix",
           "sample_meanflow_prefix"]
