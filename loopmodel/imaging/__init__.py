"""Low-level image processing shared by the front end, the observers and the readers.

Pyramidal KLT tracking (``klt.py``) and stereo rectification (``rectify.py``); nothing here
depends on a pipeline stage, so every stage may use it.
"""
