"""Training: one loop (`loop.py`: seeding, split, schedule, exact resume, atomic checkpoints,
Ctrl-C, non-finite stop) and one small module per model on top of it: `odmo`, `a2m`, `dvgan`
and `classifier` (the evaluation classifier)."""
