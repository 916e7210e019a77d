"""PyTorch reference for `cargo bench -p guardian-lab --bench train_throughput`.

The same network as guardian's embedding net (`--picture`: the picture network; otherwise pen features, "same" convolutions over time
with ReLU, max pool of 2 after every layer but the last, global mean and max over time
concatenated, a linear layer, L2 normalisation), the same batch-all triplet loss on squared
distances averaged over the active triplets, and AdamW with the same settings, on the
batches the bench wrote (real drawings). Prints `samples/s N` (one sample = one sequence's
forward + backward + optimiser share). Install: `pip install torch`.
"""

import argparse
import struct
import time

import torch
import torch.nn.functional as F


def load(path):
    with open(path, "rb") as f:
        n, b, l, c = struct.unpack("<4I", f.read(16))
        batches = []
        for _ in range(n):
            x = torch.frombuffer(bytearray(f.read(4 * b * l * c)), dtype=torch.float32)
            y = torch.frombuffer(bytearray(f.read(4 * b)), dtype=torch.int32)
            batches.append((x.reshape(b, l, c).clone(), y.clone().long()))
    return batches, c


class PictureNet(torch.nn.Module):
    """guardian's picture network: per layer a "same" 3x3 convolution, ReLU and a 2x2 max
    pool; the global mean, a linear layer, L2 normalisation."""

    def __init__(self, channels, kernel, embed_dim):
        super().__init__()
        self.convs = torch.nn.ModuleList()
        c_in = 1
        for c in channels:
            self.convs.append(torch.nn.Conv2d(c_in, c, kernel, padding=kernel // 2))
            c_in = c
        self.fc = torch.nn.Linear(c_in, embed_dim)

    def forward(self, x):
        b, pixels, _ = x.shape
        side = int(round(pixels ** 0.5))
        h = x.reshape(b, 1, side, side)
        for conv in self.convs:
            h = F.max_pool2d(F.relu(conv(h)), 2)
        return F.normalize(self.fc(h.mean((2, 3))), dim=1, eps=1e-6)


class Net(torch.nn.Module):
    def __init__(self, c_in, channels, kernel, embed_dim):
        super().__init__()
        self.convs = torch.nn.ModuleList()
        for c in channels:
            self.convs.append(torch.nn.Conv1d(c_in, c, kernel, padding=kernel // 2))
            c_in = c
        self.fc = torch.nn.Linear(2 * c_in, embed_dim)

    def forward(self, x):
        h = x.transpose(1, 2)  # [B, C, L]
        for i, conv in enumerate(self.convs):
            h = F.relu(conv(h))
            if i + 1 < len(self.convs):
                h = F.max_pool1d(h, 2)
        pooled = torch.cat([h.mean(2), h.amax(2)], 1)
        return F.normalize(self.fc(pooled), dim=1, eps=1e-6)


def batch_all(e, labels, margin):
    d = (torch.cdist(e, e) ** 2).clamp_min(0)
    same = labels[:, None] == labels[None, :]
    eye = torch.eye(len(labels), dtype=torch.bool)
    pos = same & ~eye
    neg = ~same
    t = F.relu(d[:, :, None] - d[:, None, :] + margin) * (pos[:, :, None] & neg[:, None, :])
    active = (t > 1e-12).sum().clamp_min(1)
    return t.sum() / active


def main():
    p = argparse.ArgumentParser()
    p.add_argument("data")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--channels", default="32,64,128")
    p.add_argument("--kernel", type=int, default=5)
    p.add_argument("--embed-dim", type=int, default=128)
    p.add_argument("--margin", type=float, default=0.2)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--picture", action="store_true", help="the picture network")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(1)
    batches, c_in = load(a.data)
    channels = [int(v) for v in a.channels.split(",")]
    if a.picture:
        net = PictureNet(channels, a.kernel, a.embed_dim)
    else:
        net = Net(c_in, channels, a.kernel, a.embed_dim)
    opt = torch.optim.AdamW(net.parameters(), lr=a.lr, weight_decay=a.weight_decay)

    def step(i):
        x, y = batches[i % len(batches)]
        opt.zero_grad(set_to_none=True)
        loss = batch_all(net(x), y, a.margin)
        loss.backward()
        opt.step()
        return len(y)

    for i in range(3):
        step(i)
    samples = 0
    t0 = time.perf_counter()
    for i in range(a.steps):
        samples += step(i)
    secs = time.perf_counter() - t0
    print(f"samples/s {samples / secs:.1f}")


if __name__ == "__main__":
    main()
