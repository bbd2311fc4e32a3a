"""How close a bank's objects are to a real ground-truth database's, per class (the
paper's FID, Table 4, and the point-cloud generation literature's feature-free set).

- sets.py: both databases streamed into per-class fixed-size object sets;
- metrics.py: Chamfer-based MMD, coverage and 1-NN accuracy, Wasserstein-1 distances,
  the Fréchet distance and its bootstrap interval;
- encoder.py: the PointNet-style encoder (torch, imported lazily) whose features the
  Fréchet distance compares;
- score.py: everything per class for a bank folder and a real info pickle.
"""
