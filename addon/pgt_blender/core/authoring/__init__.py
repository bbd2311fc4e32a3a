"""Pipeline step 2: author the object (source frame -> object frame).

Object frame: +x forward (the heading), +y left, +z up, metres, origin at the centre
of the object's axis-aligned box. Every step returns the (4, 4) transform it applied;
their product is ``object_from_source``, so a bank object can be replayed and audited
back to the file it came from.

``alignment``  PCA axes (rigid)          ``heading``  front/back quarter turns (rigid)
``sizing``     class sizes (scale)       ``heading_classifier``  learned front/back (torch)
``prepare``    the chain, headless
"""
