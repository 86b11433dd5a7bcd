"""Open3D's voxel grid and clustering on one PCD file, for `cargo bench --bench stages_vs_pcl`.

Usage: python3 open3d_stages.py VOXEL_IN.pcd CLUSTER_IN.pcd LEAF TOLERANCE RUNS

Prints one JSON object: Open3D's version, `voxel_down_sample(LEAF)` on VOXEL_IN (its output
count and best wall time of RUNS, ms) and `cluster_dbscan(eps=TOLERANCE, min_points=1)` on
CLUSTER_IN (cluster sizes, best wall time, ms). Non-finite points are removed first (outside
the timing: Open3D's bounds would be NaN). Open3D anchors its grid at the cloud's minimum
bound where PCL anchors at the origin, so its voxel count differs slightly from PCL's; DBSCAN
with min_points 1 joins points within eps (PCL: strictly below), so its components are PCL's
Euclidean clusters but for ties at exactly the tolerance. Install: `pip install
open3d-cpu==0.19.0`.
"""

import json
import sys
import time

import numpy as np
import open3d as o3d


def best_ms(runs, f):
    best = float("inf")
    out = None
    for _ in range(runs):
        start = time.perf_counter()
        out = f()
        best = min(best, (time.perf_counter() - start) * 1e3)
    return best, out


def main():
    voxel_in, cluster_in, leaf, tol, runs = sys.argv[1:6]
    leaf, tol, runs = float(leaf), float(tol), int(runs)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    cloud = o3d.io.read_point_cloud(voxel_in).remove_non_finite_points()
    voxel_ms, voxels = best_ms(runs, lambda: cloud.voxel_down_sample(leaf))
    cloud = o3d.io.read_point_cloud(cluster_in).remove_non_finite_points()
    cluster_ms, labels = best_ms(
        runs, lambda: np.asarray(cloud.cluster_dbscan(eps=tol, min_points=1))
    )
    sizes = sorted(np.bincount(labels[labels >= 0]).tolist(), reverse=True)
    print(
        json.dumps(
            {
                "version": o3d.__version__,
                "voxel_ms": voxel_ms,
                "voxel_points": len(voxels.points),
                "cluster_ms": cluster_ms,
                "cluster_sizes": sizes,
            }
        )
    )


if __name__ == "__main__":
    main()
