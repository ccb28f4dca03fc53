"""The ground floor: what every other part of the service builds on, importing nothing of it.

Quaternion maths (:mod:`.quaternion`), samples and blocks (:mod:`.samples`), the sample clock
(:mod:`.sample_clock`), sensor calibration (:mod:`.calibration`), row and state layouts
(:mod:`.layout`), vibration levels (:mod:`.vibration`), configuration checkers
(:mod:`.settings`) and path checks (:mod:`.paths`). Floors and conventions: docs/design.md.
"""
