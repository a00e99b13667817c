"""Whole cycles, blocks of whole cycles and whole-cycle windows (torchconn.cycles), against
phases whose cycles are known in closed form."""

import math

import pytest
import torch

from torchconn.cycles import (
    block_masks,
    centred_window,
    cycle_blocks,
    cycle_index,
    cycle_number,
    present_cycles,
    rank_blocks,
    trials_apart,
    whole_cycle_phase,
    whole_cycle_weights,
)
from torchconn.phase import unwrap

F64 = torch.float64
TWO_PI = 2 * math.pi


def ramp(cycles: float, per_cycle: int = 100, start: float = 0.0) -> torch.Tensor:
    """A phase advancing uniformly over ``cycles`` cycles, ``per_cycle`` samples each, the
    samples half a step off the cycle boundaries."""
    n = round(cycles * per_cycle)
    return start + TWO_PI * (torch.arange(n, dtype=F64) + 0.5) / per_cycle


def counts(block: torch.Tensor, n: int) -> list[int]:
    return [int((block == f).sum()) for f in range(n)]


def test_a_ramp_of_7_5_cycles_splits_into_blocks_of_whole_cycles():
    phase = ramp(7.5)
    cyc = cycle_number(phase)
    assert cyc.tolist() == [t // 100 for t in range(750)]
    # 8 cycles 0 … 7 (the last a half): blocks ⌊3k/8⌋ hold cycles 0-2, 3-5 and 6-7
    block = cycle_blocks(phase, 3)
    assert block.tolist() == [(t // 100) * 3 // 8 for t in range(750)]
    assert counts(block, 3) == [300, 300, 150]
    # block_masks: one block per sample
    assert block_masks(block, 3).sum(-1).eq(1).all()


def test_the_centred_window_holds_the_whole_cycles_in_the_middle():
    phase = ramp(7.5)
    mono, start, n = centred_window(phase)
    span = (phase[-1] - phase[0]) / TWO_PI  # 7.49 cycles between the first and last samples
    assert float(n) == 7.0
    assert torch.equal(mono, phase)
    assert float(start) == pytest.approx(float(phase[0]) + math.pi * (float(span) - 7))
    w = whole_cycle_weights(phase)
    assert float(w.sum()) == pytest.approx(700.0, abs=1e-9)  # 7 cycles of 100 samples
    assert float(w[0]) == 0.0 and float(w[-1]) == 0.0 and float(w[375]) == 1.0
    # blocks ⌊3k/7⌋ of the window's cycles: 3, 2, 2; the samples before and after the window
    # join the first and last blocks
    block = cycle_blocks(phase, 3, span="centred")
    lead = int(((phase < start) | (phase > start + TWO_PI * n)).sum())
    got = counts(block, 3)
    assert sum(got) == 750 and lead in (49, 50, 51)
    assert abs(got[0] - (300 + 25)) <= 1 and got[1] == 200 and abs(got[2] - (200 + 25)) <= 1
    assert torch.all(block.diff() >= 0)
    # the weighted mean of a periodic function of the phase is its cycle average
    assert float((w * torch.cos(phase)).sum() / w.sum()) == pytest.approx(0.0, abs=1e-3)


def test_a_missing_phase_has_no_cycle_or_block_unless_asked_for_the_first():
    phase = ramp(3.0)
    phase[[0, 1, 150]] = torch.nan
    cyc = cycle_number(phase)
    assert torch.isnan(cyc[[0, 1, 150]]).all()
    assert cycle_index(phase, False)[[0, 1, 150]].tolist() == [-1, -1, -1]
    assert cycle_index(phase, False, missing="first")[[0, 1, 150]].tolist() == [0, 0, 0]
    block = cycle_blocks(phase, 3)
    assert block[[0, 1, 150]].tolist() == [-1, -1, -1]
    assert not block_masks(block, 3)[[0, 1, 150]].any()
    # the origin is the smallest finite phase (sample 2): cycles 0, 1, 2 of 100 samples,
    # shifted by the two samples before it
    assert cycle_index(phase, False)[2:].tolist() == [
        -1 if t == 150 else (t - 2) // 100 for t in range(2, 300)]


def test_the_origin_is_the_smallest_or_first_finite_phase_or_the_2pi_grid():
    # a phase that steps back below its first value: "min" counts from the lowest phase,
    # "first" from the first finite one (the step back is cycle -1, or 0 as "missing='first'")
    phase = torch.tensor([math.nan, 1.0, 1.0 + 3.0, 1.0 - 0.5, 1.0 + 7.0], dtype=F64)
    assert cycle_number(phase, origin="min")[1:].tolist() == [0.0, 0.0, 0.0, 1.0]
    assert cycle_number(phase, origin="first")[1:].tolist() == [0.0, 0.0, -1.0, 1.0]
    assert cycle_index(phase, False, origin="first", missing="first").tolist() == [0, 0, 0, 0, 1]
    # "grid": cycles start at the multiples of 2π (⌊φ / 2π⌋ = 0, 1, 2, 1), from the lowest
    grid = torch.tensor([1.0, 7.0, 13.0, 12.0], dtype=F64)
    assert cycle_number(grid, origin="grid").tolist() == [0.0, 1.0, 2.0, 1.0]
    assert cycle_number(grid, origin="min").tolist() == [0.0, 0.0, 1.0, 1.0]


def test_pooled_trials_are_numbered_apart_by_the_widest_trial_or_cumulatively():
    # three trials of 2, 3 and 1 whole cycles (the third padded with NaN)
    trials = [ramp(2.0, 10), ramp(3.0, 10), ramp(1.0, 10)]
    phase = torch.full((3, 30), math.nan, dtype=F64)
    for b, p in enumerate(trials):
        phase[b, :len(p)] = p
    own = cycle_index(phase, False)
    widest = cycle_index(phase, True).reshape(3, 30)
    cumulative = cycle_index(phase, True, offset="cumulative").reshape(3, 30)
    for b, (w_off, c_off) in enumerate([(0, 0), (3, 2), (6, 5)]):
        ok = own[b] >= 0
        assert torch.equal(widest[b][ok], own[b][ok] + w_off)
        assert torch.equal(cumulative[b][ok], own[b][ok] + c_off)
        assert (widest[b][~ok] == -1).all() and (cumulative[b][~ok] == -1).all()
    assert sorted(set(cumulative[cumulative >= 0].tolist())) == list(range(6))


def test_interval_samples_take_the_cycle_of_their_first_sample_through_a_pool():
    # two trials, 3 and 2 cycles from different starting phases, one wrapped: an interval of
    # h = 2 samples takes its first sample's cycle; pooled, the second trial's cycles follow
    k = torch.arange(31, dtype=F64)
    phase = torch.stack([0.5 + k * (2 * math.pi / 9.7),  # cycles start at k = 0, 10, 20
                         torch.remainder(4.0 + k * (2 * math.pi / 14.7), 2 * math.pi)])  # 0, 15
    first = unwrap(phase)[..., :-2]
    cyc = cycle_index(first, False, origin="first", missing="first")
    assert cyc.shape == (2, 29)
    assert cyc[0].tolist() == [j // 10 for j in range(29)]
    assert cyc[1].tolist() == [j // 15 for j in range(29)]
    pooled = cycle_index(first, True, origin="first", missing="first", offset="cumulative")
    assert pooled.tolist() == cyc[0].tolist() + (cyc[1] + 3).tolist()


def test_blocks_of_a_list_of_cycles_go_by_rank_and_of_samples_by_cycle_number():
    # trial 0 keeps cycles 0, 4, 5, 6 (1-3 dropped); trial 1 keeps 0-3
    trial = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1])
    index = torch.tensor([6, 0, 5, 4, 0, 1, 2, 3])
    assert rank_blocks(trial, index, 2).tolist() == [1, 0, 1, 0, 0, 0, 1, 1]
    # by cycle number (⌊2k / 7⌋) cycle 4 would be in the second block
    phase = torch.tensor([c * TWO_PI + 1.0 for c in (0, 4, 5, 6)], dtype=F64)
    assert cycle_blocks(phase, 2).tolist() == [0, 1, 1, 1]


def test_present_cycles_number_the_cycles_of_the_mask_over_the_trials():
    # 10 samples a cycle; the first sample, and trial 0's fourth, moved off the half-step grid
    # so that no sample lies on a cycle boundary from either origin
    phase = torch.stack([ramp(3.0, 10), ramp(3.0, 10, start=2.0)])
    phase[:, 0] -= TWO_PI * 0.03
    phase[0, 3] -= TWO_PI * 0.02
    mask = torch.ones(2, 30, dtype=torch.bool)
    mask[0, :3] = False  # the first 3 samples of trial 0 are unusable
    mask[1, 20:27] = False  # trial 1's last cycle keeps 3 samples
    cycle, trials, index = present_cycles(phase, mask.clone())
    assert trials == [0, 0, 0, 1, 1, 1] and index == [0, 1, 2, 0, 1, 2]
    assert cycle[0, :3].tolist() == [-1] * 3
    assert cycle[0, 3:].tolist() == [0] * 7 + [1] * 10 + [2] * 10
    kept = mask.clone()
    cycle, trials, index = present_cycles(phase, kept, min_samples=4)
    assert trials == [0, 0, 0, 1, 1] and not kept[1, 27:].any() and (cycle[1, 27:] == -1).all()
    # from the first usable sample, trial 0's cycles start 3 samples later
    cycle, _, index = present_cycles(phase, mask.clone(), origin="mask")
    assert cycle[0, 3:].tolist() == [0] * 10 + [1] * 10 + [2] * 7 and index[:3] == [0, 1, 2]


def test_a_phase_with_drop_outs_is_filled_and_weighs_nothing_there():
    phase = ramp(4.0, 50)
    phase[[0, 1, 60, 61, 62]] = torch.nan
    filled, w = whole_cycle_phase(phase)
    assert torch.isfinite(filled).all() and torch.all(filled.diff() >= 0)
    assert filled[:2].tolist() == [float(phase[2])] * 2
    assert filled[60:63].tolist() == [float(phase[59])] * 3
    assert w[[0, 1, 60, 61, 62]].eq(0).all()
    assert torch.equal(w, whole_cycle_weights(filled) * torch.isfinite(phase).to(F64))


def test_trials_moved_apart_share_no_cycle_and_keep_their_place_in_it():
    phase = torch.stack([ramp(2.0, 10), ramp(3.0, 10, start=-1.0)[:20]])
    apart = trials_apart(phase)
    assert torch.allclose(torch.remainder(apart - phase, TWO_PI),
                          torch.zeros_like(phase), atol=1e-9)
    cyc = torch.floor(apart / TWO_PI)
    assert set(cyc[0].tolist()).isdisjoint(cyc[1].tolist())
    assert float(apart[1].min()) > float(apart[0].max())


@pytest.mark.parametrize("call", [
    lambda p: cycle_number(p, origin="last"),
    lambda p: cycle_index(p, True, missing="drop"),
    lambda p: cycle_index(p, True, offset="own"),
    lambda p: cycle_blocks(p, 3, span="window"),
    lambda p: present_cycles(p[None], torch.ones(1, p.shape[-1], dtype=torch.bool), origin="x"),
])
def test_an_unknown_rule_is_refused_by_name(call):
    with pytest.raises(ValueError, match="must be"):
        call(ramp(2.0))
