"""Reinforcement learning with the learned model (supplementary F.3): off-policy agents (DDPG,
SVG(0), SVG(N) through the learned model), their replay buffer and observation graphs, on the
Gymnasium vector environments of ``gnwarp.control``."""
