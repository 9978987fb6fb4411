"""The Decision Transformer network (Chen et al. 2021), from torch's own transformer modules.

A trajectory ``(R_1, s_1, a_1, R_2, s_2, a_2, ...)`` becomes three tokens per step: linear
embeddings of the return-to-go ``R_t``, the state and the action, each plus a learned embedding of
the episode timestep ``t`` (the only positional information, as in the reference code, which
removes GPT-2's position embeddings). A GPT-style stack (pre-LayerNorm blocks, causal
self-attention, ReLU MLPs of 4x width, dropout, a final LayerNorm) reads them; the action ``a_t``
is predicted from the hidden state of the token ``s_t``, so it sees ``R_1..R_t``, ``s_1..s_t`` and
``a_1..a_{t-1}``, never ``a_t`` itself. Actions are predicted in [-1, 1] (tanh).
"""

from __future__ import annotations

import torch
from torch import nn

TOKENS_PER_STEP = 3  # return-to-go, state, action


class DecisionTransformerModel(nn.Module):
    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        max_timestep: int,
        embed_dim: int = 128,
        n_layers: int = 3,
        n_heads: int = 1,
        dropout: float = 0.1,
    ):
        super().__init__()
        self.embed_timestep = nn.Embedding(max_timestep, embed_dim)
        self.embed_return = nn.Linear(1, embed_dim)
        self.embed_state = nn.Linear(obs_dim, embed_dim)
        self.embed_action = nn.Linear(act_dim, embed_dim)
        self.embed_ln = nn.LayerNorm(embed_dim)
        self.embed_dropout = nn.Dropout(dropout)
        block = nn.TransformerEncoderLayer(
            embed_dim,
            n_heads,
            dim_feedforward=4 * embed_dim,
            dropout=dropout,
            activation="relu",
            batch_first=True,
            norm_first=True,  # GPT-2's pre-LayerNorm blocks
        )
        self.blocks = nn.TransformerEncoder(
            block, n_layers, norm=nn.LayerNorm(embed_dim), enable_nested_tensor=False
        )
        self.predict_action = nn.Sequential(nn.Linear(embed_dim, act_dim), nn.Tanh())
        for module in self.blocks.modules():  # GPT-2's initialisation inside the transformer
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=0.02)
                nn.init.zeros_(module.bias)
        self.max_timestep = max_timestep
        self._masks: dict[tuple[int, torch.device], torch.Tensor] = {}

    def _causal_mask(self, length: int, device: torch.device) -> torch.Tensor:
        key = (length, device)
        if key not in self._masks:
            self._masks[key] = nn.Transformer.generate_square_subsequent_mask(length, device=device)
        return self._masks[key]

    def forward(
        self,
        returns_to_go: torch.Tensor,  # (B, K) scaled
        states: torch.Tensor,  # (B, K, obs_dim) normalized
        actions: torch.Tensor,  # (B, K, act_dim) in [-1, 1]
        timesteps: torch.Tensor,  # (B, K) long
    ) -> torch.Tensor:
        """Predicted actions ``(B, K, act_dim)``: entry ``t`` from the tokens up to ``s_t``.

        Sequences shorter than K are padded *after* their last step; with causal attention the
        padding never reaches a real step, so no padding mask is needed (only a loss mask).
        """
        batch, steps = states.shape[:2]
        time = self.embed_timestep(timesteps)
        tokens = torch.stack(
            (
                self.embed_return(returns_to_go.unsqueeze(-1)) + time,
                self.embed_state(states) + time,
                self.embed_action(actions) + time,
            ),
            dim=2,
        ).reshape(batch, TOKENS_PER_STEP * steps, -1)
        x = self.embed_dropout(self.embed_ln(tokens))
        length = TOKENS_PER_STEP * steps
        hidden = self.blocks(x, mask=self._causal_mask(length, x.device), is_causal=True)
        state_tokens = hidden.reshape(batch, steps, TOKENS_PER_STEP, -1)[:, :, 1]
        return self.predict_action(state_tokens)
