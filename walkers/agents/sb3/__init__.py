"""Stable-Baselines3's (and sb3-contrib's) twins behind the Agent interface: ``arguments`` maps
walkers' hyperparameters to SB3's, ``twin`` wraps the model."""
