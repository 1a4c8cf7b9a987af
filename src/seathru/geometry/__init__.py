"""Camera geometry shared by pose recovery, dataset readers and evaluation. Pure numpy.

- ``poses``: axis conventions, similarity alignment, trajectory comparison, near/far bounds,
  scene normalisation;
- ``intrinsics``: focal lengths known before SfM (user, EXIF) and the initial COLMAP camera;
- ``quality``: the SfM quality policy (gate, plan of attempts, agreement between models,
  which model to keep);
- ``upright``: the vertical of the world frame from the cameras (open water above the horizon
  tells the veiling light; below it, it may be far seabed).
"""
