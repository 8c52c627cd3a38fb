"""``afmctl view``: a local web page that watches running scanners over zenoh.

:mod:`.feed` subscribes to the zenoh keys of docs/ZENOH.md (setpoints, drift, status and the
simulator's ``sim/tip`` and ``sim/image``) and keeps a decimated, bounded picture of each
scanner; :mod:`.app` serves it to browsers over a websocket (starlette + uvicorn); the page
itself is ``static/`` (no CDN: everything ships in the package). See docs/VIEW.md.
"""
