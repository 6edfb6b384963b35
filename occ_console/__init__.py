"""occ-console: the web staff console (issue 13).

A separate process that watches and commands OCC daemons as an ordinary OpenIGTLink operator
client of each (``link.py``), keeps what it learns per daemon (``model.py``) and serves a page,
a JSON API and server-sent events on this machine (``app.py``, Starlette on uvicorn;
``cli.py`` is the command). Nothing in ``igtl`` or ``occ`` imports it.
"""
