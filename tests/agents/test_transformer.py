"""The Decision Transformer's network: GPT-2's blocks, equal to torch's own pre-LayerNorm encoder
on the same weights, and causal (an action never sees itself or anything after it)."""

from __future__ import annotations

import torch
from torch import nn

from walkers.agents.common.transformer import DecisionTransformerModel

OBS, ACT, STEPS, BATCH = 5, 2, 8, 3


def _model(dropout: float = 0.0, n_heads: int = 2) -> DecisionTransformerModel:
    torch.manual_seed(0)
    return DecisionTransformerModel(
        OBS, ACT, 50, embed_dim=16, n_layers=2, n_heads=n_heads, dropout=dropout
    )


def _inputs(seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(BATCH, STEPS, generator=g),
        torch.randn(BATCH, STEPS, OBS, generator=g),
        torch.rand(BATCH, STEPS, ACT, generator=g) * 2 - 1,
        torch.randint(0, 50, (BATCH, STEPS), generator=g),
    )


def test_blocks_equal_torchs_pre_layernorm_encoder_on_the_same_weights():
    model = _model().eval()
    layer = nn.TransformerEncoderLayer(16, 2, 64, 0.0, "relu", batch_first=True, norm_first=True)
    torch_encoder = nn.TransformerEncoder(
        layer, 2, norm=nn.LayerNorm(16), enable_nested_tensor=False
    )
    for theirs, ours in zip(torch_encoder.layers, model.blocks, strict=True):
        theirs.norm1.load_state_dict(ours.ln_attention.state_dict())
        theirs.self_attn.in_proj_weight.data.copy_(ours.attention.qkv.weight)
        theirs.self_attn.in_proj_bias.data.copy_(ours.attention.qkv.bias)
        theirs.self_attn.out_proj.load_state_dict(ours.attention.proj.state_dict())
        theirs.norm2.load_state_dict(ours.ln_mlp.state_dict())
        theirs.linear1.load_state_dict(ours.mlp[0].state_dict())
        theirs.linear2.load_state_dict(ours.mlp[2].state_dict())
    torch_encoder.norm.load_state_dict(model.final_ln.state_dict())
    torch_encoder.eval()
    x = torch.randn(BATCH, 3 * STEPS, 16)
    mask = nn.Transformer.generate_square_subsequent_mask(3 * STEPS)
    with torch.no_grad():
        expected = torch_encoder(x, mask=mask, is_causal=True)
        assert torch.allclose(model.final_ln(model.blocks(x)), expected, atol=1e-6)


def test_an_action_is_predicted_from_what_came_before_it_only():
    model = _model().eval()
    returns, states, actions, timesteps = _inputs()
    with torch.no_grad():
        before = model(returns, states, actions, timesteps)
        t = 4  # change a_t and everything after step t: predictions up to a_t stay
        later_actions, later_states = actions.clone(), states.clone()
        later_actions[:, t:] = -later_actions[:, t:]
        later_states[:, t + 1 :] += 1.0
        after = model(returns, later_states, later_actions, timesteps)
    assert torch.equal(before[:, : t + 1], after[:, : t + 1])
    assert not torch.allclose(before[:, t + 1 :], after[:, t + 1 :])


def test_dropout_acts_in_training_only():
    model = _model(dropout=0.5)
    inputs = _inputs()
    model.train()
    assert not torch.equal(model(*inputs), model(*inputs))
    model.eval()
    with torch.no_grad():
        assert torch.equal(model(*inputs), model(*inputs))
