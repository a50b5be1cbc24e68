"""What goes in and out as files: datasets and their columns, MODEL.json files, provenance and
figures.

Nothing here runs at import time; the pure packages import the column names from here without
pulling in file handling.
"""
