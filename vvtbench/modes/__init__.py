"""Image-space mode identification: streamed spectra, peaks, sampling at mesh vertices.

See ``docs/modes.md`` for the pipeline and the file format.
"""

from ..video.files import open_video
from .damping import damping_half_power, damping_lorentzian
from .extract import confidence_weights, extract_modes, modes_from_displacements
from .joint import extract_joint, joint_modes, modal_phasors
from .mac import mac
from .merging import merge_modes
from .modeset import ModeSet, merge_modesets
from .peaks import align_phase, check_band, pick_peaks, translation_mac
from .sampling import (
    camera_from_clicks,
    estimate_camera,
    load_clicks,
    observation_operator,
    sample_field,
    sample_modes,
)
from .spectrum import DisplacementStore, bin_fields, motion_power_spectrum

__all__ = [
    "DisplacementStore",
    "ModeSet",
    "align_phase",
    "bin_fields",
    "camera_from_clicks",
    "check_band",
    "confidence_weights",
    "damping_half_power",
    "damping_lorentzian",
    "estimate_camera",
    "extract_joint",
    "extract_modes",
    "joint_modes",
    "load_clicks",
    "mac",
    "merge_modes",
    "merge_modesets",
    "modal_phasors",
    "modes_from_displacements",
    "motion_power_spectrum",
    "observation_operator",
    "open_video",
    "pick_peaks",
    "sample_field",
    "sample_modes",
    "translation_mac",
]
