"""Pilot on natural:600's labelled layouts only (no validation, no test panel): which training settings
generalise to held-out layouts? 5-fold by layout; first-ranked success, chance, ceiling, AUC."""
import sys, time
from pathlib import Path
import numpy as np, torch
from torch import nn
from scenegen.experiment.proposal_data import examples
from scenegen.experiment.proposal_labels import label_layouts, open_labels
from scenegen.policy.proposal_model import ProposalNet, ProposalModel

torch.set_num_threads(1)
labels = Path(sys.argv[3] if len(sys.argv) > 3 else "runs/proposal_labels")
config, store, views = open_labels(labels)
scenes = list(label_layouts(["natural:600"], None)["natural:600"])
data = examples(scenes, store, views, labels / "crops", config)
if "--cat" in sys.argv:  # the requested category as a one-hot beside the numbers
    import scenegen.policy.proposal_model as pm
    from scenegen.assets.catalog import load_catalog
    from scenegen.env.scenes import scene_sha256
    catalog = load_catalog(); cats = sorted(set(catalog.categories))
    cat_of = {scene_sha256(s): catalog.get(next(o for o in s.objects if o.name == s.target).asset).category for s in scenes}
    onehot = np.array([[float(cat_of[sha] == c) for c in cats] for sha in data.scene], np.float32)
    data.features = np.concatenate([data.features, onehot], axis=1); pm.FEATURES = data.features.shape[1]
if "--v2" in sys.argv:
    import scenegen.policy.proposal_model as pm
    v2 = np.load("runs/proposals_pilot/v2.npz")["features"]
    assert len(v2) == len(data), (len(v2), len(data))
    data.features = v2; pm.FEATURES = v2.shape[1]
order = list(dict.fromkeys(data.scene)); scene = np.array([order.index(s) for s in data.scene])
folds = int(sys.argv[2]) if len(sys.argv) > 2 else 5

def rank_loss(logits, y, groups):
    """Listwise: per layout with a success and a failure, -log of the softmax mass on its successes."""
    total, n = logits.new_zeros(()), 0
    for g in torch.unique(groups):
        m = groups == g; yy = y[m]
        if 0 < yy.sum() < len(yy):
            s = logits[m]; total = total - torch.logsumexp(s[yy > 0], 0) + torch.logsumexp(s, 0); n += 1
    return total / max(n, 1)

def train(idx, steps, wd=0.0, drop=0.0, flip=False, feats_only=False, width=16, seed=0, rank=0.0):
    torch.manual_seed(seed); g = torch.Generator().manual_seed(seed)
    net = ProposalNet(width)
    if drop: net.head = nn.Sequential(nn.Dropout(drop), *net.head)
    x = torch.from_numpy(data.crops[idx]); f = torch.from_numpy(data.features[idx]); y = torch.from_numpy(data.labels[idx])
    if feats_only: x = torch.zeros_like(x)
    pos = max(float(y.sum()), 1.0); w = torch.tensor((len(y) - pos) / pos).clamp(1, 20)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=wd); loss_fn = nn.BCEWithLogitsLoss(pos_weight=w)
    net.train()
    for _ in range(steps):
        i = torch.randint(len(y), (64,), generator=g); xb = x[i]
        if flip:  # a parallel gripper's heading and its reverse: the crop turned 180 degrees
            turn = (torch.rand(64, generator=g) < 0.5) & (f[i][:, 0] > 0.5)  # top grasps only
            xb = torch.where(turn[:, None, None, None], xb.flip(2, 3), xb)
            fb = f[i].clone(); fb[turn, 6:11] *= -1  # heading-signed features reversed
        else:
            fb = f[i]
        loss = loss_fn(net(xb, fb), y[i])
        if rank:
            lay = torch.from_numpy(np.unique(scene[idx]))
            pick = lay[torch.randint(len(lay), (12,), generator=g)]
            j = torch.from_numpy(np.where(np.isin(scene[idx], pick.numpy()))[0])
            loss = loss + rank * rank_loss(net(x[j], f[j]), y[j], torch.from_numpy(scene[idx])[j])
        opt.zero_grad(); loss.backward(); opt.step()
    net.eval(); return net, feats_only

def evaluate(net, feats_only, idx):
    with torch.no_grad():
        x = torch.from_numpy(data.crops[idx]); x = torch.zeros_like(x) if feats_only else x
        s = torch.sigmoid(net(x, torch.from_numpy(data.features[idx]))).numpy()
    y = data.labels[idx]; sc = scene[idx]; first, chance, ceil = [], [], []
    for k in np.unique(sc):
        m = sc == k; first.append(y[m][np.argmax(s[m])]); chance.append(y[m].mean()); ceil.append(y[m].max())
    pos, neg = s[y == 1], s[y == 0]
    auc = (pos[:, None] > neg[None, :]).mean() + 0.5 * (pos[:, None] == neg[None, :]).mean()
    return np.array([np.mean(first), np.mean(chance), np.mean(ceil), auc]) * np.array([len(first)] * 3 + [1])

variants = {
    "cnn3000": dict(steps=3000), "cnn800": dict(steps=800), "cnn800_wd": dict(steps=800, wd=0.05, drop=0.3),
    "cnn1500_flip_wd": dict(steps=1500, wd=0.05, drop=0.3, flip=True), "feats1500": dict(steps=1500, feats_only=True),
    "feats800": dict(steps=800, feats_only=True), "cnn3000_flip_wd": dict(steps=3000, wd=0.05, drop=0.3, flip=True),
    "cnn3000_flip_wd_w32": dict(steps=3000, wd=0.05, drop=0.3, flip=True, width=32),
    "rank1500": dict(steps=1500, wd=0.05, drop=0.3, flip=True, rank=1.0),
    "rank1500_feats": dict(steps=1500, feats_only=True, rank=1.0),
}
chosen = sys.argv[1].split(",") if len(sys.argv) > 1 else list(variants)
for name in chosen:
    t0 = time.process_time(); total = np.zeros(4); n = 0
    for k in range(folds):
        test = scene % folds == k
        net, fo = train(np.where(~test)[0], **variants[name])
        r = evaluate(net, fo, np.where(test)[0]); n += r[0] / max(r[0] / len(np.unique(scene[test])), 1e-9) if False else len(np.unique(scene[test])); total += r
    print(f"{name}: first-ranked {total[0]/n:.3f} chance {total[1]/n:.3f} ceiling {total[2]/n:.3f} AUC {total[3]/folds:.3f} "
          f"({n} layouts, {time.process_time()-t0:.0f} CPU-s)", flush=True)
