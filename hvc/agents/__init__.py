"""Networks: MLP policies and critics (low level), encoders and the LSTM core (high level)."""
