"""The published numbers the report compares with: the paper's tables and figures, and the authors' notebooks."""

from __future__ import annotations

# H.2, Table 2: learned (μ, e) of the homogeneous tasks
TABLE2 = {
    "BP5-e": {"CM-CD-CLNN": (0, 1), "CM-CD-CHNN": (0, 1), "CMr-CD-CLNN": (0, 1), "CMr-CD-CHNN": (0, 1)},
    "CP3-e": {"CM-CD-CLNN": (0, 1), "CM-CD-CHNN": (0, 1), "CMr-CD-CLNN": (0.0016, 1), "CMr-CD-CHNN": (0.0020, 1)},
    "CP3": {
        "CM-CD-CLNN": (0.4998, 0.0048),
        "CM-CD-CHNN": (0.5000, 0.0038),
        "CMr-CD-CLNN": (0.5004, 0.0229),
        "CMr-CD-CHNN": (0.5005, 0.0229),
    },
    "Rope": {
        "CM-CD-CLNN": (0, 0.2322),
        "CM-CD-CHNN": (0, 0.2277),
        "CMr-CD-CLNN": (0, 0.4437),
        "CMr-CD-CHNN": (0, 0.5041),
    },
    "Gyro-e": {
        "CM-CD-CLNN": (1.0168, 0.6430),
        "CM-CD-CHNN": (0.9174, 0.6535),
        "CMr-CD-CLNN": (0.0024, 1),
        "CMr-CD-CHNN": (0.0024, 1),
    },
    "Gyro": {
        "CM-CD-CLNN": (0.8764, 0.6569),
        "CM-CD-CHNN": (0.9216, 0.6556),
        "CMr-CD-CLNN": (0.0994, 0.8918),
        "CMr-CD-CHNN": (0.0994, 0.8934),
    },
}

# H.6: learned (μ, e) of the models trained on noisy data (single checkpoints; "failed" where the authors say so), by
# noise std. Only CP3-e, CP3 and BP5-e were published.
NOISE = {
    0.01: {
        "CP3-e": {"CM-CD-CLNN": (0.0009, 1), "CMr-CD-CLNN": (0.0038, 1)},
        "CP3": {"CM-CD-CLNN": (0.4951, 0.0180), "CMr-CD-CLNN": (0.4959, 0.0361)},
        "BP5-e": {"CM-CD-CLNN": (0, 0.9266), "CMr-CD-CLNN": (0.0024, 0.9712)},
    },
    0.05: {
        "CP3-e": {"CM-CD-CLNN": (0, 0.9978), "CMr-CD-CLNN": (0.0036, 1)},
        "CP3": {"CM-CD-CLNN": (0.4353, 0.0632), "CMr-CD-CLNN": (0.4618, 0.0608)},
        "BP5-e": {"CM-CD-CLNN": (0, 0.0373), "CMr-CD-CLNN": (0.4460, 0.2435)},
    },
}

# H.3: the per-slot vectors of CM-CD-CLNN (10 pairs, then 20 ball-wall slots)
SLOTS = {
    "BP5": {
        "mu": [0.4996, 0.4000, 0.5998, 0.8002, 0.8998, 1.1003, 1.1074, 0.1001, 0.0216, 0.3002,
               0.1001, 0.1003, 0.0998, 0.0999, 0.1001, 0.1003, 1.8333, 0.0998, 0.0998, 0.0998,
               0.0998, 0.1000, 0.1008, 0.1007, 0.0997, 0.1054, 0.1002, 0.8652, 0.1001, 0.1002],
        "e": [0.1000, 0.2000, 0.3000, 0.4000, 0.5000, 0.6000, 1.0000, 0.8000, 0.7711, 1.0000,
              0.8001, 0.8000, 0.8000, 0.8000, 0.8001, 0.8000, 0.8294, 0.7999, 0.8000, 0.8000,
              0.7999, 0.7999, 0.7992, 0.7761, 0.8000, 0.6935, 0.8001, 0.8122, 0.8000, 0.8000],
    },
    "BD5": {
        "mu": [1.3501, 0.8330, 0.0000, 0.6771, 1.0727, 1.0604, 0.9455, 0.0000, 0.2395, 0.7198,
               0.2692, 0.2621, 0.2413, 0.2410, 0.1307, 0.1228, 0.1272, 0.1279, 1.1990, 0.1205,
               0.1163, 0.1243, 0.1233, 0.1220, 0.1216, 0.1124, 0.1201, 0.1190, 0.1200, 0.1193],
        "e": [0.3174, 0.4515, 0.1348, 0.9323, 0.8303, 0.2855, 0.9615, 0.9000, 0.6908, 0.0014,
              0.7759, 0.7501, 0.8000, 0.7994, 0.6973, 0.7936, 0.7580, 0.7664, 0.8712, 0.7963,
              0.8698, 0.7282, 0.7795, 0.8006, 0.7942, 0.7937, 0.7745, 0.7675, 0.7618, 0.7930],
    },
}  # fmt: skip

# H.4: learned mass / learned mass of body 0
MASS_RATIO = {
    "BP5-e": {
        "CM-CD-CLNN": [1, 1.0000, 1.0000, 1.0002, 1.0003],
        "CMr-CD-CLNN": [1, 1.0000, 0.9993, 0.9991, 0.9989],
        "CM-CD-CHNN": [1, 0.9998, 1.0000, 1.0000, 1.0000],
        "CMr-CD-CHNN": [1, 1.0004, 0.9994, 0.9999, 0.9997],
    },
    "BP5": {
        "CM-CD-CLNN": [1, 2.0001, 6.0036, 8.0014, 10.0024],
        "CMr-CD-CLNN": [1, 1.9998, 6.0004, 8.0033, 9.9997],
        "CM-CD-CHNN": [1, 2.0005, 6.0020, 8.0015, 10.0029],
        "CMr-CD-CHNN": [1, 2.0002, 6.0001, 7.9985, 10.0010],
    },
    "BD5": {"CM-CD-CLNN": [1, 3.3003, 10.510, 14.014, 17.804]},
    "CP3-e": {
        "CM-CD-CLNN": [1, 0.6500, 0.7502],
        "CMr-CD-CLNN": [1, 0.6500, 0.7521],
        "CM-CD-CHNN": [1, 0.6499, 0.7500],
        "CMr-CD-CHNN": [1, 0.6503, 0.7526],
    },
    "CP3": {
        "CM-CD-CLNN": [1, 2.0006, 1.4990],
        "CMr-CD-CLNN": [1, 2.0002, 1.5001],
        "CM-CD-CHNN": [1, 1.9996, 1.4994],
        "CMr-CD-CHNN": [1, 2.0009, 1.5009],
    },
}

# H.5: the 5-step trajectory error (mean, 95 % half width) on CM-generated data: CM-CD-CLNN on four tasks, and every
# model on the ropes of 50, 100 and 200 nodes
TRAJECTORY_ERROR = {
    "BP5-e": {"CM-CD-CLNN": (2.341e-5, 1.285e-5)},
    "CP3": {"CM-CD-CLNN": (3.848e-3, 9.51e-4)},
    "CP3-e": {"CM-CD-CLNN": (2.832e-3, 3.64e-4)},
    "Gyro": {"CM-CD-CLNN": (2.389e-3, 1.357e-3)},
    # the rope scaling (ER{n}k50, every model)
    "Rope50": {
        "CM-CD-CLNN": (1.973e-3, 4.73e-4),
        "MLP-CD-CLNN": (1.847e-2, 2.53e-3),
        "IN-CP-CLNN": (2.306e-2, 2.12e-3),
        "IN-CP-SP": (2.932e-2, 2.05e-3),
    },
    "Rope100": {
        "CM-CD-CLNN": (9.39e-4, 3.26e-4),
        "MLP-CD-CLNN": (1.081e-2, 8.9e-4),
        "IN-CP-CLNN": (1.268e-2, 7.8e-4),
        "IN-CP-SP": (1.374e-2, 8.1e-4),
    },
    "Rope200": {
        "CM-CD-CLNN": (3.198e-3, 5.69e-4),
        "MLP-CD-CLNN": (5.984e-3, 5.21e-4),
        "IN-CP-CLNN": (6.870e-3, 5.11e-4),
        "IN-CP-SP": (8.938e-3, 5.30e-4),
    },
}

ELASTIC = ("BP5-e", "CP3-e", "Gyro-e")  # the Fig. 5 panels

# H.5: sample efficiency on the rope of 200 nodes (ER200k50): the 5-step error against the training trajectories
EFFICIENCY_SIZES = (25, 50, 100, 200, 400, 800, 1600, 3200, 6400, 12800)
_CURVES = {
    "CM-CD-CLNN": (1.915e-3, 1.866e-3, 2.036e-3, 1.922e-3, 1.897e-3, 3.198e-3, 2.268e-3, 1.639e-3, 1.571e-3, 1.202e-3),
    "MLP-CD-CLNN": (2.956e-2, 1.248e-2, 7.358e-3, 8.662e-3, 7.024e-3, 5.984e-3, 5.944e-3, 5.980e-3, 5.921e-3, 5.935e-3),
    "IN-CP-CLNN": (3.729e-2, 3.063e-2, 2.100e-2, 2.685e-2, 1.438e-2, 6.870e-3, 6.863e-3, 6.213e-3, 5.903e-3, 5.902e-3),
    "IN-CP-SP": (5.964e-2, 6.493e-2, 2.817e-2, 3.588e-2, 2.711e-2, 8.938e-3, 9.188e-3, 7.328e-3, 7.718e-3, 7.397e-3),
}
SAMPLE_EFFICIENCY = {"Rope200": {model: dict(zip(EFFICIENCY_SIZES, curve)) for model, curve in _CURVES.items()}}
