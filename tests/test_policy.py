"""Policy: shapes for every variant and image size, GRU state resets, signature checks."""

from __future__ import annotations

import pytest
import torch

from findview_baselines.rl.policy import (
    NUM_ACTIONS,
    VARIANTS,
    Policy,
    build_policy,
    check_signature,
    conv_output_size,
)


def random_obs(batch: int, height: int, width: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "view": torch.randint(0, 256, (batch, 3, height, width), dtype=torch.uint8, generator=g),
        "target": torch.randint(0, 256, (batch, 3, height, width), dtype=torch.uint8, generator=g),
    }


def take(obs: dict[str, torch.Tensor], rows) -> dict[str, torch.Tensor]:
    return {k: v[rows] for k, v in obs.items()}


# --------------------------------------------------------------------------------------------------
# Shapes
# --------------------------------------------------------------------------------------------------


def test_conv_output_size_matches_hand_computation() -> None:
    # 256: (256-8)//4+1 = 63 -> (63-4)//2+1 = 30 -> 30-3+1 = 28
    assert conv_output_size(256, 256) == (28, 28)
    # 192: 47 -> 22 -> 20
    assert conv_output_size(192, 256) == (20, 28)
    # 64: 15 -> 6 -> 4
    assert conv_output_size(64, 64) == (4, 4)
    with pytest.raises(ValueError, match="too small"):
        conv_output_size(32, 32)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("size", [(64, 64), (256, 256), (192, 256)])
def test_act_shapes(variant: str, size: tuple[int, int]) -> None:
    torch.manual_seed(0)
    height, width = size
    hidden_size = 32
    policy = Policy(height, width, variant=variant, hidden_size=hidden_size)
    n = 2
    obs = random_obs(n, height, width)
    hidden = policy.initial_hidden(n)
    masks = torch.zeros(n)
    with torch.no_grad():
        actions, log_probs, values, new_hidden = policy.act(obs, hidden, masks)
        value_only = policy.get_value(obs, hidden, masks)
    assert actions.shape == (n,) and actions.dtype == torch.long
    assert ((actions >= 0) & (actions < NUM_ACTIONS)).all()
    assert log_probs.shape == (n,) and (log_probs <= 0).all()
    assert values.shape == (n,)
    assert new_hidden.shape == (n, hidden_size)
    torch.testing.assert_close(value_only, values)


def test_default_sizes_and_feature_widths() -> None:
    policy = Policy(128, 128)  # paper defaults: early fusion, 512
    assert policy.encoder.convs[0].in_channels == 6
    assert policy.encoder.fc[0].out_features == 512
    assert policy.gru.input_size == 512 and policy.gru.hidden_size == 512
    assert policy.actor.out_features == 5 and policy.critic.out_features == 1

    goal = Policy(64, 64, variant="goal_encoder", hidden_size=16)
    assert goal.gru.input_size == 32 and goal.goal_encoder.convs[0].in_channels == 3
    siamese = Policy(64, 64, variant="siamese", hidden_size=16)
    assert siamese.encoder.convs[0].in_channels == 3 and siamese.gru.input_size == 16


def test_unknown_variant_and_wrong_image_size() -> None:
    with pytest.raises(ValueError, match="unknown policy variant"):
        Policy(64, 64, variant="late_fusion")
    policy = Policy(64, 64, hidden_size=16)
    with pytest.raises(ValueError, match="64x64"):
        policy.act(random_obs(1, 72, 72), policy.initial_hidden(1), torch.ones(1))


def test_siamese_shares_encoder_weights_across_view_and_target() -> None:
    """Swapping view and target must change features only through the fuse layer order."""
    torch.manual_seed(0)
    policy = Policy(64, 64, variant="siamese", hidden_size=16)
    obs = random_obs(3, 64, 64)
    view_feat = policy.encoder(obs["view"].float() / 255)
    target_feat = policy.encoder(obs["target"].float() / 255)
    expected = policy.fuse(torch.cat([view_feat, target_feat], dim=1))
    torch.testing.assert_close(policy.encode(obs), expected)


def test_deterministic_act_is_argmax_and_repeatable() -> None:
    torch.manual_seed(0)
    policy = Policy(64, 64, hidden_size=16)
    with torch.no_grad():  # make the policy far from uniform
        policy.actor.bias.copy_(torch.tensor([0.0, 0.0, 3.0, 0.0, 0.0]))
    obs = random_obs(4, 64, 64)
    hidden, masks = policy.initial_hidden(4), torch.zeros(4)
    with torch.no_grad():
        a1, lp1, _, _ = policy.act(obs, hidden, masks, deterministic=True)
        a2, lp2, _, _ = policy.act(obs, hidden, masks, deterministic=True)
    assert (a1 == 2).all() and torch.equal(a1, a2) and torch.equal(lp1, lp2)


# --------------------------------------------------------------------------------------------------
# Recurrent state
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_policy() -> Policy:
    torch.manual_seed(1)
    return Policy(64, 64, variant="early_fusion", hidden_size=16)


def test_mask_zero_resets_hidden_in_act(small_policy: Policy) -> None:
    obs = random_obs(2, 64, 64)
    stale = torch.randn(2, 16)
    with torch.no_grad():
        _, _, v_reset, h_reset = small_policy.act(obs, stale, torch.zeros(2), deterministic=True)
        _, _, v_zero, h_zero = small_policy.act(obs, torch.zeros(2, 16), torch.ones(2), deterministic=True)
        _, _, v_kept, _ = small_policy.act(obs, stale, torch.ones(2), deterministic=True)
    torch.testing.assert_close(v_reset, v_zero)
    torch.testing.assert_close(h_reset, h_zero)
    assert not torch.allclose(v_kept, v_zero)


def test_evaluate_actions_resets_mid_sequence_like_two_halves(small_policy: Policy) -> None:
    """T=6, N=2; env 0 starts a new episode at t=3, env 1 runs through. Compare with separate runs."""
    T, N, H = 6, 2, 16
    obs = random_obs(T * N, 64, 64, seed=3)  # time-major rows: t * N + env
    actions = torch.randint(0, NUM_ACTIONS, (T * N,), generator=torch.Generator().manual_seed(4))
    hidden0 = torch.randn(N, H, generator=torch.Generator().manual_seed(5))
    masks = torch.ones(T, N)
    masks[3, 0] = 0.0
    with torch.no_grad():
        lp, v, ent = small_policy.evaluate_actions(obs, hidden0, masks.flatten(), actions)
    assert lp.shape == v.shape == ent.shape == (T * N,)
    lp, v, ent = lp.view(T, N), v.view(T, N), ent.view(T, N)

    def rows(env: int, t0: int, t1: int) -> list[int]:
        return [t * N + env for t in range(t0, t1)]

    with torch.no_grad():
        # env 0, first half from hidden0[0], second half from a zero state (mask 0 at its first step)
        a_lp, a_v, a_ent = small_policy.evaluate_actions(
            take(obs, rows(0, 0, 3)), hidden0[:1], torch.ones(3), actions[rows(0, 0, 3)]
        )
        b_lp, b_v, b_ent = small_policy.evaluate_actions(
            take(obs, rows(0, 3, 6)), torch.zeros(1, H), torch.ones(3), actions[rows(0, 3, 6)]
        )
        # env 1 alone, whole sequence, never reset
        c_lp, c_v, c_ent = small_policy.evaluate_actions(
            take(obs, rows(1, 0, 6)), hidden0[1:], torch.ones(6), actions[rows(1, 0, 6)]
        )
    torch.testing.assert_close(lp[:, 0], torch.cat([a_lp, b_lp]))
    torch.testing.assert_close(v[:, 0], torch.cat([a_v, b_v]))
    torch.testing.assert_close(ent[:, 0], torch.cat([a_ent, b_ent]))
    torch.testing.assert_close(lp[:, 1], c_lp)
    torch.testing.assert_close(v[:, 1], c_v)
    torch.testing.assert_close(ent[:, 1], c_ent)


def test_step_by_step_act_matches_evaluate_actions(small_policy: Policy) -> None:
    """Rolling out with act() and re-evaluating the rollout in one call give the same numbers."""
    T, N = 5, 3
    obs = random_obs(T * N, 64, 64, seed=7)
    masks = torch.ones(T, N)
    masks[0] = 0.0
    masks[2, 1] = 0.0
    masks[4, 2] = 0.0
    hidden0 = torch.zeros(N, 16)
    torch.manual_seed(8)
    hidden = hidden0
    actions, log_probs, values = [], [], []
    with torch.no_grad():
        for t in range(T):
            a, lp, v, hidden = small_policy.act(take(obs, slice(t * N, (t + 1) * N)), hidden, masks[t])
            actions.append(a)
            log_probs.append(lp)
            values.append(v)
        e_lp, e_v, _ = small_policy.evaluate_actions(obs, hidden0, masks.flatten(), torch.cat(actions))
    torch.testing.assert_close(e_lp, torch.cat(log_probs))
    torch.testing.assert_close(e_v, torch.cat(values))


# --------------------------------------------------------------------------------------------------
# Signature
# --------------------------------------------------------------------------------------------------


def test_signature_roundtrip_and_mismatch_messages() -> None:
    a = Policy(64, 64, variant="early_fusion", hidden_size=16)
    assert a.model_signature() == {"variant": "early_fusion", "hidden_size": 16, "height": 64, "width": 64}
    check_signature(a.model_signature(), a.model_signature())

    b = Policy(64, 64, variant="siamese", hidden_size=16)
    with pytest.raises(ValueError, match=r"variant is 'early_fusion' in the checkpoint but 'siamese'"):
        check_signature(a.model_signature(), b.model_signature())

    c = Policy(72, 64, hidden_size=16)
    with pytest.raises(ValueError, match=r"height is 64 in the checkpoint but 72"):
        check_signature(a.model_signature(), c.model_signature())

    with pytest.raises(ValueError, match=r"no field 'width'"):
        check_signature({"variant": "early_fusion", "hidden_size": 16, "height": 64}, a.model_signature())


def test_build_policy_from_agent_config(repo_root) -> None:
    from findview_baselines.cli import compose_config, validate_config

    cfg = validate_config(compose_config("train", ["agent=ppo"])).agent
    assert cfg.name == "ppo" and cfg.variant == "early_fusion" and cfg.hidden_size == 512
    cfg.hidden_size = 16
    cfg.variant = "goal_encoder"
    policy = build_policy(cfg, 64, 64)
    assert policy.model_signature() == {"variant": "goal_encoder", "hidden_size": 16, "height": 64, "width": 64}


# --------------------------------------------------------------------------------------------------
# The correlation variant and the auxiliary rotation head
# --------------------------------------------------------------------------------------------------


def test_early_fusion_weights_keep_their_names() -> None:
    """Checkpoints of the paper's variant stay loadable: the same parameter names as before."""
    policy = Policy(64, 64, variant="early_fusion", hidden_size=16)
    expected = {f"encoder.convs.{i}.{p}" for i in (0, 2, 4) for p in ("weight", "bias")}
    expected |= {"encoder.fc.0.weight", "encoder.fc.0.bias", "actor.weight", "actor.bias"}
    expected |= {"critic.weight", "critic.bias"}
    expected |= {f"gru.{k}_{g}_l0" for k in ("weight", "bias") for g in ("ih", "hh")}
    assert set(policy.state_dict()) == expected


def test_correlation_volume_peaks_at_the_shift() -> None:
    """Target maps = view maps moved by +2 cells along x: the +2 displacement bin matches."""
    torch.manual_seed(0)
    policy = Policy(64, 64, variant="correlation", hidden_size=16)
    enc = policy.encoder
    g = enc.grid[0]
    assert enc.grid == (8, 8) and enc.shifts == (15, 15)
    view = torch.randn(2, 32, g, g)
    same = enc.correlation(view, view)
    rolled = enc.correlation(view, torch.roll(view, shifts=2, dims=3))
    centre = g - 1  # bin of displacement 0
    # identical maps: cosine 1 for every pair at displacement 0
    torch.testing.assert_close(same[:, 0, centre, centre], torch.ones(2))
    torch.testing.assert_close(same[:, 1, centre, centre], torch.ones(2))
    # rolled (a permutation of the cells, so the same centring): target cell (i, j + 2) is view cell
    # (i, j), and with the wrap-around target cell (i, j - 6) is view cell (i, j) too: both bins are 1,
    # every other bin is below
    torch.testing.assert_close(rolled[:, 0, centre, centre + 2], torch.ones(2))
    torch.testing.assert_close(rolled[:, 0, centre, centre - 6], torch.ones(2))
    others = rolled[:, 0].clone()
    others[:, centre, [centre + 2, centre - 6]] = -1.0
    assert (others < 0.99).all()
    # shifted without wrap (two new columns enter on the left): the +2 bin wins
    shifted = torch.cat([torch.randn(2, 32, g, 2), view[..., :-2]], dim=3)
    rolled = enc.correlation(view, shifted)
    assert rolled[:, 0].flatten(1).argmax(dim=1).tolist() == [centre * 15 + centre + 2] * 2
    # the log-count channel: g*g pairs at displacement 0 (-> 1), one pair at the corners (-> 0)
    assert rolled[0, 2, centre, centre].item() == pytest.approx(1.0)
    assert rolled[0, 2, 0, 0].item() == pytest.approx(0.0)
    # the soft readout points the same way: expected dx > 0, dy ~ 0
    soft = enc.soft_shift(rolled)
    assert (soft[:, 1] > 0.05).all() and (soft[:, 0].abs() < soft[:, 1]).all()


def test_correlation_mask_reset_and_gradients_reach_every_weight() -> None:
    torch.manual_seed(2)
    policy = Policy(48, 48, variant="correlation", hidden_size=16)
    obs = random_obs(2, 48, 48)
    stale = torch.randn(2, 16)
    with torch.no_grad():
        _, _, v_reset, h_reset = policy.act(obs, stale, torch.zeros(2), deterministic=True)
        _, _, v_zero, h_zero = policy.act(obs, torch.zeros(2, 16), torch.ones(2), deterministic=True)
    torch.testing.assert_close(v_reset, v_zero)
    torch.testing.assert_close(h_reset, h_zero)

    T, N = 3, 2
    seq = random_obs(T * N, 48, 48, seed=4)
    dist, values, _, features = policy.forward_features(seq, torch.zeros(N, 16), torch.ones(T * N))
    assert features.shape == (T * N, policy.feature_size)
    (dist.logits.pow(2).sum() + values.pow(2).sum()).backward()
    no_grad = [name for name, p in policy.named_parameters() if p.grad is None or not bool(p.grad.abs().sum() > 0)]
    assert no_grad == []


def shifted_pairs(n: int, generator: torch.Generator, size: int = 32) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """View and target crops of smooth random strips; the target is the view's strip shifted by
    ``s`` in [-12, 12] \\ {0} pixels (label dyaw = s / size, overlap 1) or, for a quarter of the pairs, a
    crop of another strip (overlap 0)."""
    strips = torch.rand(n, 3, size // 4, 3 * size // 4, generator=generator)
    strips = torch.nn.functional.interpolate(strips, scale_factor=4, mode="bilinear", align_corners=False)
    shift = torch.randint(1, 13, (n,), generator=generator) * (torch.randint(0, 2, (n,), generator=generator) * 2 - 1)
    x0 = size
    view = torch.stack([strips[i, :, :, x0 : x0 + size] for i in range(n)])
    target = torch.stack([strips[i, :, :, x0 + int(shift[i]) : x0 + int(shift[i]) + size] for i in range(n)])
    other = torch.arange(n) < n // 4
    target[other] = target[other].roll(1, dims=0)  # another pair's target: nothing in common
    labels = torch.stack([torch.zeros(n), shift.float() / size, (~other).float()], dim=1)
    labels[other, :2] = 0.0
    to_u8 = lambda x: (x * 255).round().to(torch.uint8)  # noqa: E731
    return {"view": to_u8(view), "target": to_u8(target)}, labels


def test_aux_head_learns_the_sign_of_a_yaw_shift() -> None:
    from findview_baselines.rl.policy import AuxHead, aux_loss

    torch.manual_seed(0)
    old_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        policy = Policy(32, 32, variant="correlation", hidden_size=32)
        head = AuxHead(policy.feature_size)
        opt = torch.optim.Adam(list(policy.parameters()) + list(head.parameters()), lr=2e-3)
        g = torch.Generator().manual_seed(1)
        first = None
        for step in range(150):
            obs, labels = shifted_pairs(32, g)
            terms = aux_loss(head(policy.encode(obs)), labels)
            first = terms["loss"].item() if first is None else first
            opt.zero_grad()
            terms["loss"].backward()
            opt.step()
        with torch.no_grad():
            obs, labels = shifted_pairs(256, torch.Generator().manual_seed(99))
            pred = head(policy.encode(obs))
            terms = aux_loss(pred, labels)
    finally:
        torch.set_num_threads(old_threads)
    overlap = labels[:, 2] == 1
    sign_acc = (pred[overlap, 1].sign() == labels[overlap, 1].sign()).float().mean().item()
    assert terms["loss"].item() < 0.5 * first
    assert sign_acc > 0.9
    assert terms["overlap_accuracy"].item() > 0.8


def test_aux_loss_by_hand() -> None:
    from findview_baselines.rl.policy import aux_loss

    pred = torch.tensor([[0.0, 0.5, 0.0], [1.0, 1.0, 0.0]])
    targets = torch.tensor([[0.0, 0.2, 1.0], [0.0, 0.0, 0.0]])  # row 1 does not overlap: no rotation term
    terms = aux_loss(pred, targets)
    # smooth L1 (beta 0.1) of 0.3: 0.3 - 0.05 = 0.25; BCE of logit 0 is log 2 for both rows
    assert terms["rotation_loss"].item() == pytest.approx(0.25)
    assert terms["overlap_loss"].item() == pytest.approx(torch.log(torch.tensor(2.0)).item())
    assert terms["loss"].item() == pytest.approx(0.25 + 0.6931472, rel=1e-5)
