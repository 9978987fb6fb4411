"""The Decision Transformer network (Chen et al. 2021): GPT-2's blocks as its reference code
uses them.

A trajectory ``(R_1, s_1, a_1, R_2, s_2, a_2, ...)`` becomes three tokens per step: linear
embeddings of the return-to-go ``R_t``, the state and the action, each plus a learned embedding of
the episode timestep ``t`` (the only positional information, as in the reference code, which
removes GPT-2's position embeddings). A GPT-2 stack reads them: pre-LayerNorm blocks of causal
self-attention and a ReLU MLP of 4x width, dropout on the embeddings, the attention weights and
each block's two residual branches (never inside the MLP: torch's ``nn.TransformerEncoderLayer``
adds one there, which GPT-2 has not and which cost a sixth of a CPU step), a final LayerNorm, and
GPT-2's initialisation (normal 0.02, the residual projections scaled by 1/sqrt(2 x blocks)). The
action ``a_t`` is predicted from the hidden state of the token ``s_t``, so it sees
``R_1..R_t``, ``s_1..s_t`` and ``a_1..a_{t-1}``, never ``a_t`` itself. Actions are predicted in
[-1, 1] (tanh).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

TOKENS_PER_STEP = 3  # return-to-go, state, action
INIT_STD = 0.02  # GPT-2's initializer_range


class CausalSelfAttention(nn.Module):
    """GPT-2's attention: one fused q, k, v projection, causal scaled dot-product attention
    (dropout on its weights while training), the output projection, residual dropout."""

    def __init__(self, embed_dim: int, n_heads: int, dropout: float):
        super().__init__()
        self.qkv = nn.Linear(embed_dim, 3 * embed_dim)
        self.proj = nn.Linear(embed_dim, embed_dim)
        self.n_heads, self.attention_dropout = n_heads, dropout
        self.residual_dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, length, width = x.shape
        heads = self.qkv(x).view(batch, length, 3, self.n_heads, width // self.n_heads)
        q, k, v = heads.permute(2, 0, 3, 1, 4)  # each (batch, heads, length, head width)
        dropout = self.attention_dropout if self.training else 0.0
        y = F.scaled_dot_product_attention(q, k, v, dropout_p=dropout, is_causal=True)
        return self.residual_dropout(self.proj(y.transpose(1, 2).reshape(batch, length, width)))


class Block(nn.Module):
    """x + attention(LN(x)), then x + MLP(LN(x)): GPT-2's pre-LayerNorm block."""

    def __init__(self, embed_dim: int, n_heads: int, dropout: float):
        super().__init__()
        self.ln_attention = nn.LayerNorm(embed_dim)
        self.attention = CausalSelfAttention(embed_dim, n_heads, dropout)
        self.ln_mlp = nn.LayerNorm(embed_dim)
        self.mlp = nn.Sequential(
            nn.Linear(embed_dim, 4 * embed_dim),
            nn.ReLU(),
            nn.Linear(4 * embed_dim, embed_dim),
            nn.Dropout(dropout),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attention(self.ln_attention(x))
        return x + self.mlp(self.ln_mlp(x))

    def residual_projections(self) -> tuple[nn.Linear, nn.Linear]:
        """GPT-2's ``c_proj`` layers: the two that write into the residual stream."""
        return self.attention.proj, self.mlp[2]


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
        self.blocks = nn.Sequential(*(Block(embed_dim, n_heads, dropout) for _ in range(n_layers)))
        self.final_ln = nn.LayerNorm(embed_dim)
        self.predict_action = nn.Sequential(nn.Linear(embed_dim, act_dim), nn.Tanh())
        for module in self.blocks.modules():  # GPT-2's initialisation inside the transformer
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=INIT_STD)
                nn.init.zeros_(module.bias)
        for block in self.blocks:
            for projection in block.residual_projections():
                nn.init.normal_(projection.weight, std=INIT_STD / math.sqrt(2 * n_layers))
        self.max_timestep = max_timestep

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
        hidden = self.final_ln(self.blocks(x))
        state_tokens = hidden.reshape(batch, steps, TOKENS_PER_STEP, -1)[:, :, 1]
        return self.predict_action(state_tokens)
