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

import logging
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

TOKENS_PER_STEP = 3  # return-to-go, state, action
INIT_STD = 0.02  # GPT-2's initializer_range
#: ``algo.precision``: the dtype the transformer runs in under autocast (None: plain fp32)
PRECISIONS = {"fp32": None, "bf16": torch.bfloat16}


#: CPU flags of native bfloat16 matmuls (x86): without one, bf16 autocast is emulated and slow
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_has_native_bf16(cpuinfo: str | None = None) -> bool | None:
    """Whether this CPU multiplies bfloat16 natively (``/proc/cpuinfo``'s flags, or ``cpuinfo``
    given); None where that cannot be told (not Linux, not x86)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return None
    lines = [line for line in cpuinfo.splitlines() if line.startswith("flags")]
    if not lines:  # not x86 (an ARM CPU lists "Features"): unknown here, so no warning
        return None
    flags = {f for line in lines for f in line.split()}
    return any(flag in flags for flag in NATIVE_BF16_FLAGS)


def warn_if_slow_precision(device: torch.device, precision: str) -> None:
    """bf16 on a CPU without native bfloat16 matmuls is emulated: measured 10.7x slower a DT step
    than fp32 on an AMD EPYC without AVX-512 BF16 (1.57x faster on one with it). Say so once,
    at the start of the run, rather than let a user wait."""
    if precision == "bf16" and device.type == "cpu" and cpu_has_native_bf16() is False:
        logging.getLogger("walkers").warning(
            "algo.precision=bf16 on a CPU without %s: bfloat16 is emulated here, about 10x "
            "slower than fp32 (algo.precision=fp32)",
            " or ".join(NATIVE_BF16_FLAGS),
        )


def autocast(device: torch.device, precision: str):
    """The context the transformer runs in: bfloat16 autocast for ``bf16`` (matmuls and
    attention in bfloat16, reductions, LayerNorm and the weights in fp32), nothing for ``fp32``."""
    dtype = PRECISIONS[precision]
    return torch.autocast(device.type, dtype=dtype or torch.float32, enabled=dtype is not None)


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
