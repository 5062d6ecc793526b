import numpy as np, pycolmap, torch, time

def root_sift(d):
    d = d.astype(np.float32)
    d /= np.maximum(d.sum(1, keepdims=True), 1e-9)
    return np.sqrt(d)

def kmeans(x, k, iters=10, seed=0):
    g = np.random.default_rng(seed)
    c = x[g.choice(len(x), k, replace=False)].copy()
    xt = torch.from_numpy(x)
    for _ in range(iters):
        ct = torch.from_numpy(c)
        a = (xt @ ct.T * 2 - (ct * ct).sum(1)).argmax(1).numpy()
        for j in range(k):
            m = a == j
            if m.any(): c[j] = x[m].mean(0)
    return c

def vlad(descs, centres):
    ct = torch.from_numpy(centres)
    out = []
    for d in descs:
        dt = torch.from_numpy(d)
        a = (dt @ ct.T * 2 - (ct * ct).sum(1)).argmax(1)
        v = torch.zeros_like(ct).index_add_(0, a, dt - ct[a])
        v = v / v.norm(dim=1, keepdim=True).clamp_min(1e-9)  # intra-normalisation
        v = v.flatten()
        out.append((v / v.norm().clamp_min(1e-9)).numpy())
    return np.stack(out)

def pairs(database, names, k, words=64, per_image=300):
    t = time.perf_counter()
    db = pycolmap.Database.open(database)
    ids = {im.name: im.image_id for im in db.read_all_images()}
    descs = [root_sift(np.asarray(db.read_descriptors(ids[n]).data)) for n in names]
    db.close()
    g = np.random.default_rng(0)
    sample = np.concatenate([d[g.choice(len(d), min(len(d), per_image), replace=False)] for d in descs])
    centres = kmeans(sample, words)
    v = vlad(descs, centres)
    sim = v @ v.T
    np.fill_diagonal(sim, -np.inf)
    sel = set()
    for i in range(len(names)):
        for j in np.argsort(-sim[i])[:k]:
            sel.add((min(i, j), max(i, j)))
    print("retrieval", time.perf_counter() - t, len(sel))
    return [(names[a], names[b]) for a, b in sorted(sel)]
