"""Evaluation reports of a run directory: ``report.html`` (self-contained, figures embedded) and ``report.md``.

:func:`reports.render.render_report` is the entry point; :mod:`reports.figures` draws the figures (matplotlib,
Agg) in the fixed palette of :mod:`reports.colours`; :mod:`reports.document` is the document tree that
:mod:`reports.html` and :mod:`reports.markdown` render. ``reports`` reads results files only: the gallery
pictures (re-run trials) and the regression verdicts are handed in by ``harness report``.
"""
