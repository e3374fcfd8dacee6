"""The steppers of each structure family that live outside its structure module: one module
per family (Lie–Poisson, log-canonical) and the learned realizations."""
