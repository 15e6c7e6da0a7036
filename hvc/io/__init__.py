"""Files a run writes, below every layer that trains (runtime's high-level loop and the
low-level expert trainer alike): atomic writes and checkpoints (`checkpoint`), and the
long-format metrics.csv with its TensorBoard twin (`metrics`). Imports nothing of hvc but
hvc.errors, so any layer may use it."""
