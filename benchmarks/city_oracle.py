"""The alignment alone, with an oracle for the network: merged camera error against per-chunk noise.

    python benchmarks/city_oracle.py [--views 120] [--chunk 16] [--overlap 4]

Each chunk gets the ground-truth cameras and depth points of its views in its own random Sim(3) frame, perturbed
by noise ``n``: camera rotations ~ N(0, 30 n) degrees, camera centres ~ N(0, n x extent), depth points along their
rays by a factor 1 + N(0, n). Prints camera errors after one global Sim(3) fit, for the chained pairwise fits and
after the pose graph (which differ only where the plan has more edges than a chain, e.g. overlap > chunk / 2).
"""

from __future__ import annotations

import argparse

from _bench import positive_int

from anycity.city import align_chunks, plan_chunks
from anycity.city.oracle import camera_errors, oracle_chunks, orbit_scene
from anycity.city.plan import owners


def merged(chunks, S, plan):
    import torch

    from anycity.city import w2c_to_world

    own = owners(plan)
    return torch.stack([w2c_to_world(chunks[k].w2c[chunks[k].views.index(v)], S[k]) for v, k in sorted(own.items())])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=positive_int, default=120)
    ap.add_argument("--chunk", type=positive_int, default=16)
    ap.add_argument("--overlap", type=int, nargs="+", default=[4, 10])
    a = ap.parse_args(argv)
    w2c, pts = orbit_scene(a.views, points_per_view=64)
    print("overlap  noise    chain: rot deg  pos/extent   graph: rot deg  pos/extent")
    for ov in a.overlap:
        plan = plan_chunks(a.views, a.chunk, ov)
        for noise in (0.0, 0.001, 0.003, 0.01, 0.03):
            chunks, _ = oracle_chunks(w2c, pts, plan, seed=0, rot_deg=30 * noise, centre_noise=noise,
                                      depth_noise=noise)
            S_c, _, _ = align_chunks(chunks, global_pass=False)
            S_g, _, _ = align_chunks(chunks)
            ec, eg = camera_errors(merged(chunks, S_c, plan), w2c), camera_errors(merged(chunks, S_g, plan), w2c)
            print(f"{ov:7d}  {noise:5.3f}   {ec['rot_deg_mean']:13.4f}  {ec['pos_rel_mean']:10.5f}   "
                  f"{eg['rot_deg_mean']:13.4f}  {eg['pos_rel_mean']:10.5f}", flush=True)


if __name__ == "__main__":
    main()
