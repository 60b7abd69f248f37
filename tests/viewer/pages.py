"""Opening the viewer in a page of its own, for tests that compare what it draws."""

from __future__ import annotations


def settled_and_evaluated(chromium, url: str, script: str, arg, *, viewport: dict,
                          screenshot=None):
    """Open ``url`` (a viewer page) in a new page, wait until its level settles, then
    evaluate ``script`` with ``arg``: (the settled status, the script's result).

    The page bypasses the viewer's CSP: GLTFLoader, which these tests draw beside
    the viewer, fetches a GLB's embedded images from blob: URLs that the viewer's
    connect-src 'self' forbids (tests/viewer/test_viewer.py checks that the viewer
    itself breaks none of its policy). A page error fails the test; ``screenshot``:
    a path the page's picture is written to."""
    page = chromium.new_page(viewport=viewport, bypass_csp=True)
    failures = []
    page.on("pageerror", lambda error: failures.append(error))
    try:
        page.goto(url)
        page.wait_for_function("() => window.lodViewer?.status().level != null")
        status = page.evaluate("lodViewer.settled()")
        result = page.evaluate(script, arg)
        if screenshot is not None:
            screenshot.write_bytes(page.screenshot())
    finally:
        page.close()
    assert not failures, failures
    return status, result
