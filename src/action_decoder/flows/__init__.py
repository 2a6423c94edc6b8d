"""The math: samplers and losses as pure functions over callables (no networks here)."""

from .ddpm import ddpm_loss, sample_ddpm
from .losses import flow_matching_loss, meanflow_loss, meanflow_target
from .paths import interpolate, score_from_velocity, time_grid, velocity_from_sample
from .rtc import (RTC_SCHEDULES, guidance_weight, meanflow_guidance, rtc_guided_velocity,
                  rtc_weights, sample_meanflow_rtc, sample_ode_rtc, sample_sde_rtc)
from .rtc_trained import delay_probs, sample_delays, sample_meanflow_prefix, sample_ode_prefix
from .samplers import (SDEResult, chain_log_prob, sample_meanflow, sample_ode, sample_sde,
                       velocity_from_meanflow)
from .sigma import ChurnSigma, ExploringSigma, FixedSigma, LearnableSigma, make_sigma

__all__ = ["RTC_SCHEDULES", "ChurnSigma", "ExploringSigma", "FixedSigma", "LearnableSigma", "SDEResult",
           "chain_log_prob", "ddpm_loss", "delay_probs", "flow_matching_loss", "interpolate", "make_sigma",
           "guidance_weight", "meanflow_loss", "meanflow_target", "meanflow_guidance",
           "rtc_guided_velocity", "rtc_weights", "sample_meanflow_rtc", "sample_ode_rtc", "sample_sde_rtc", "sample_ddpm",
           "sample_delays", "sample_meanflow_prefix", "sample_ode_prefix", "sample_meanflow", "sample_ode",
           "sample_sde", "score_from_velocity", "time_grid", "velocity_from_meanflow",
           "velocity_from_sample"]
