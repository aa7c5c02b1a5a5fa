import json, sys, numpy as np
dump, dataset = sys.argv[1], sys.argv[2]
scene = json.load(open(f"{dataset}/scene.json"))
drones = np.array([d["centre"] for d in scene["drones"]]); radii = np.array([d["radius"] for d in scene["drones"]])
for line in open(dump):
    r = json.loads(line); m = np.array(r["means"]).reshape(-1, 3)
    if not len(m): continue
    std = np.array(r["std"])[: len(m)]
    d = np.linalg.norm(m[:, None, :] - drones[None], axis=-1)
    near = (d < (radii[None] + 3 * r["voxel"])).any(1)
    f = lambda x: np.round(np.percentile(x, [10, 50, 90]), 3).tolist() if len(x) else None
    print(f"step {r['step']:4d} near {near.sum():4d} std p10/50/90 {f(std[near])}  far {(~near).sum():4d} std {f(std[~near])}  far kept at std<near p90: {int((std[~near] < np.percentile(std[near],90)).sum()) if near.any() else None}")
