"""Estimators of the array's motion: ML fusion with its Cramér–Rao bound (skog2016),
the angular-acceleration-tensor baseline, and chunked fusion of a whole stream."""
