"""``uncertsplat select-views``: which photo to take next. ``candidates`` builds candidate cameras, ``scores``
ranks them (posterior variance, FisherRF information, coverage, random)."""
