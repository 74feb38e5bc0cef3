"""Rigid-body tracking in six degrees of freedom (paper eqs. 7–14, Supp. Note 2)."""
