"""``uncertsplat view``: the model and its uncertainty in the browser.

``frames`` renders what the viewer shows (pure functions of a run and a camera); ``server`` is the viser app
around it (panel, camera frustums, the render loop); ``live`` shows a model while it trains.
"""
