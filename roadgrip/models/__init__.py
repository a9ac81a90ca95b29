"""The estimation models (paper 4.1-4.3, 5.1): DNN, CNN, ConvLSTM and SA-CNN-LSTM, each with a config dataclass, and a
registry by name. Every model maps windows (batch, time, features) to one estimate of mu per window (batch,)."""
