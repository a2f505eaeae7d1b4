"""The pipeline of one recording (placeholder while it is being written)."""

from typing import Literal, get_args

Step = Literal["calibrate", "poses", "reconstruct", "report"]
STEPS: tuple[Step, ...] = get_args(Step)
