"""The results book: every figure the README publishes, from one command (``mslam book``, ``make book``).

Owns: reading a book file (:mod:`.spec`: ``configs/book.yaml``, through the strict :mod:`.reader`), planning its
grids as runs with the configs' hashes and refusing a tuned preset on its own tuning data (:mod:`.plan`), running
them through the resumable grid and writing tables, figures, verdicts and ``book.json`` with each figure's
provenance (:mod:`.run`, :mod:`.build`, :mod:`.findings`; the shapes of its entries: :mod:`.entries`), the README's
blocks rendered from the committed ``results/book.json`` (:mod:`.readme`), and the single runs the bound tests
repeat (:mod:`.bounds`).

May import the ground floor, the doors (``ablate``) below it, ``results`` and ``report``; imported only by the CLI.
Entry points: :func:`~.spec.load_book`, :func:`~.run.run_book`, :func:`~.readme.render_file`,
:func:`~.bounds.rerun_bound`.
"""
