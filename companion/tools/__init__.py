"""Tools over recordings: replay (and its plot), the CSV format, info, convert."""
