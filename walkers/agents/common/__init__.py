"""What the algorithms share: the off-policy core (``actor_critic``), networks, Batch
Renormalization, the transformer, populations' state I/O, the on-policy Gaussian policy, PPO's
normalization, exploration noise and the non-finite-step guard. No algorithm lives here."""
