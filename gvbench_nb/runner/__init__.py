"""The runner: what stands around the protocol to add a run to an output folder.

Params files and their checks (``config``), the content-keyed stores (``store``), threads and
jobs (``concurrency``), features once per image (``image_features``), the pair loop
(``pair_matching``), one method's run (``method_runs``) and its folder (``method_outputs``),
scoring (``scoring``), the output folder's runs and what it shows (``runs``) and the Dask backend
(``distributed``).
"""
