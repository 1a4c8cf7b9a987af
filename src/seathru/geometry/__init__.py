"""Camera geometry shared by pose recovery, dataset readers and evaluation: axis conventions,
similarity alignment, trajectory comparison, near/far bounds, scene normalisation. Pure numpy.
"""
