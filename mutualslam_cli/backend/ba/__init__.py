"""The global photometric BA solver of the back end (paper §III-C).

Entry points: :func:`.global_ba.run_global_ba` (culling + BA of a front-end map, by map unit) and, beneath
it, :func:`.photometric.solve` (one photometric problem: :mod:`.problem`, :mod:`.pyramid`, :mod:`.residuals`,
:mod:`.schur`, :mod:`.lm`; the BA's targets in :mod:`.targets`). May import the ground floor, the front end's
map records (``vo``) and the back end's culling.
"""
