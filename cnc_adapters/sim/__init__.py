"""The virtual machine tool: a spindle plant, speed programs, and (later) a virtual CNC."""

from .plant import PRESETS, PlantParams, PlantRun, SpindlePlant, preset
from .programs import PROGRAMS, Program, job_shop_day, paper_calibration, program, random_validation

__all__ = [
    "PRESETS",
    "PROGRAMS",
    "PlantParams",
    "PlantRun",
    "Program",
    "SpindlePlant",
    "job_shop_day",
    "paper_calibration",
    "preset",
    "program",
    "random_validation",
]
