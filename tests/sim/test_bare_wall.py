"""The bare-wall example walk: the bench room with one long wall stripped of its cards and
photographs, filmed with the centre loop."""

from __future__ import annotations

import numpy as np

from app.sim import WALKS
from app.sim.examples import BARE_WALL_ROOM, BENCH_ROOM


def test_the_bare_wall_room_is_the_bench_room_less_one_walls_cards_and_photographs() -> None:
    for seed in range(3):
        bare, full = BARE_WALL_ROOM.walk(seed, 30, "centre_loop"), BENCH_ROOM.walk(seed, 30, "centre_loop")
        assert bare.poses == full.poses
        kept = {t.id: t for t in bare.scene.targets}
        assert 0 < len(full.scene.targets) - len(kept) < 20
        for t in full.scene.targets:
            on_bare_wall = abs(t.point(np.array([[0.5, 0.5]]))[0][1]) < 0.05  # the wall at y = 0
            assert (t.id not in kept) == on_bare_wall
            if not on_bare_wall:
                assert np.array_equal(kept[t.id].discs, t.discs)
        wall = bare.scene.background[0].texture
        assert wall.std() < 0.05 < full.scene.background[0].texture.std()  # plain paint, not photographs
        assert all(np.array_equal(a.texture, b.texture)
                   for a, b in zip(bare.scene.background[1:], full.scene.background[1:], strict=True))
        assert [t.id for t in BARE_WALL_ROOM.scene(seed).targets] == list(kept)


def test_the_bare_wall_walk_is_the_centre_loop_in_that_room() -> None:
    walk = WALKS["bare_wall"]
    assert walk.room is BARE_WALL_ROOM
    assert walk.walk(2, 40).poses == WALKS["centre_loop"].walk(2, 40).poses
