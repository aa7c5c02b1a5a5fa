import json, sys, numpy as np
dump, dataset = sys.argv[1], sys.argv[2]
scene = json.load(open(f"{dataset}/scene.json"))
drones = np.array([d["centre"] for d in scene["drones"]]); radii = np.array([d["radius"] for d in scene["drones"]])
flames = scene.get("flames")
for line in open(dump):
    r = json.loads(line)
    m = np.array(r["means"]).reshape(-1, 3)
    if len(m) == 0:
        print(r["step"], r["region"], 0); continue
    d = np.linalg.norm(m[:, None, :] - drones[None], axis=-1)  # [M, D]
    near = d < (radii[None] + 3 * r["voxel"])
    per = near.sum(0)
    print(f"step {r['step']:4d} region {r['region']} voxel {r['voxel']:.3f} carved {len(m):5d} near drones {int(near.any(1).sum()):4d} per drone {per.tolist()}")
