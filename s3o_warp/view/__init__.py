"""``s3o-view``: a fit in the browser (viser, the optional ``view`` extra).

:mod:`s3o_warp.view.run` reads a run directory into world-frame arrays (numpy only), :mod:`s3o_warp.view.server`
serves the page, :mod:`s3o_warp.view.cli` is the console script, :mod:`s3o_warp.view.browser` takes a headless
Chromium screenshot of a page (for the tests and the README's picture).
"""
