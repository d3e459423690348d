"""The view in the browser: the live measurement while it runs, and any stored session.

* :mod:`.state`: what the daemon publishes while measuring (no copies, no encoding);
* :mod:`.server`: the aiohttp server, in a thread and an event loop of its own, with its
  checks (token, Host, Origin, read-only);
* :mod:`.preview`: the frame as JPEG with the counted pixels tinted, made on demand;
* :mod:`.live`: when the daemon serves it and what it prints;
* :mod:`.replay`: a stored session as the same view (``stipi-daemon view SESSION``);
* ``static/``: the page (HTML, JS, CSS; no build step).
"""
