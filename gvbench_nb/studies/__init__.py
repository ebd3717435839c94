"""Studies: one module a analysis notebook, named after it, holding what that notebook computes
and draws."""
