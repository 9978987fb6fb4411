"""Orchestration of training: a session, its loops and per-run books, resume, checkpoints, envs,
rollouts, replays of trained policies and dataset recording."""
