"""The sharded load of `uavmm bench fusion` is what its rows say: UAVs taken in turn from each shard's
regions give every shard half the tiles, and each UAV's 3 x 3 block lies in one shard's regions."""

from __future__ import annotations

import pytest

from benchmarks.fusion_load import GRID_Z, block_tiles, blocks_of
from benchmarks.fusion_shards import balanced_blocks, blocks_owned_by, shard_shares
from shared.sharding import ShardSpec


@pytest.mark.parametrize("n", [1, 2, 7, 150])
def test_balanced_blocks_split_the_tiles_evenly_between_two_shards(n):
    blocks = balanced_blocks(n)
    assert len(blocks) == len(set(blocks)) == n
    shares = shard_shares(blocks)
    assert sum(shares) == pytest.approx(1.0)
    assert shares[0] == pytest.approx((n + 1) // 2 / n)  # UAV i over shard i % 2's regions


@pytest.mark.parametrize("shard", [0, 1])
def test_blocks_owned_by_lie_wholly_in_that_shards_regions(shard):
    spec = ShardSpec(shard, 2)
    blocks = blocks_owned_by(shard, 2, 20)
    assert len(blocks) == 20
    assert all(spec.owns(GRID_Z, x, y) for block in blocks for x, y in block_tiles(block))
    assert shard_shares(blocks)[shard] == 1.0


def test_plain_row_layout_is_what_the_hash_makes_of_it():
    """The rows-of-blocks layout is not balanced by construction: its shares come from the hash alone."""
    shares = shard_shares(blocks_of(175))
    assert sum(shares) == pytest.approx(1.0) and max(shares) > 0.5
