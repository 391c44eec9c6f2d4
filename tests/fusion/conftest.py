from dataclasses import replace

import pytest

from adaptnav.fusion.config import FilterConfig, InitialConfig, LearnedVelocityConfig, ProcessConfig


@pytest.fixture
def matched_config() -> FilterConfig:
    """Filter tuned to the test missions' truth model (constant current and k_speed)."""
    return replace(FilterConfig(),
                   initial=replace(InitialConfig(), sigma_current_m_s=0.15, sigma_k_speed=0.05),
                   process=replace(ProcessConfig(), current_rw_m_s_rthz=1e-6, k_speed_rw_rthz=1e-6),
                   learned_velocity=replace(LearnedVelocityConfig(), sigma_heave_m_s=0.01))
