"""Training-sample throughput: can the data path feed a GPU? Samples/s per core, and with DataLoader workers.

    python pipelines/generate.py --num-maps 40 --out data/bench40 --workers 0   # any dataset folder will do
    python benchmarks/samples.py --data data/bench40 --workers 0,2

Each sample cuts a chunk, goal, waypoints, local patches and heat-maps from an episode, with augmentation
(see roken/data/samples.py); batches are collated into tensors as the trainer receives them.
"""
from __future__ import annotations

import argparse
import time

import torch
from torch.utils.data import DataLoader

from roken.data.loader import ChunkDataset, collate
from roken.data.samples import EpisodeBank, SampleConfig


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="dataset folder or URI written by pipelines/generate.py")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--batches", type=int, default=20)
    p.add_argument("--workers", default="0,2", help="DataLoader worker counts to try (0 = in the main process)")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    t = time.perf_counter()
    bank = EpisodeBank.from_folder(a.data)
    print(f"loaded {len(bank)} episodes on {len(bank.map_ids)} maps in {time.perf_counter() - t:.1f} s")
    ds = ChunkDataset(bank, SampleConfig(), samples_per_epoch=a.batch * (a.batches + 2))
    for m in range(len(bank.map_ids)):
        bank.sdf(m)  # SDFs are cached per map after first use; measure the steady state
    print(f"{'workers':>7}  {'samples/s':>10}  {'per core':>9}  {'ms / batch':>10}")
    for w in [int(x) for x in a.workers.split(",")]:
        loader = DataLoader(ds, batch_size=a.batch, collate_fn=collate, num_workers=w, shuffle=True,
                            persistent_workers=False)
        it = iter(loader)
        for _ in range(2):
            next(it)  # warm-up (worker start-up)
        t = time.perf_counter()
        for _ in range(a.batches):
            next(it)
        dt = time.perf_counter() - t
        rate = a.batch * a.batches / dt
        print(f"{w:>7}  {rate:>10.0f}  {rate / max(w, 1):>9.0f}  {dt / a.batches * 1e3:>10.1f}")


if __name__ == "__main__":
    main()
