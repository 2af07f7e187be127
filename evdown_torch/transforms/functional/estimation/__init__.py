"""Linear and cubic log-luminance estimation (methods 4 and 5).

``knots`` builds each pixel's knots and the regions' breakpoints (``delay`` adds the held
knots of a bounded delay), ``linear`` and ``cubic`` solve the crossings of each curve,
``driver`` runs them over a whole stream or a stacked batch, and ``stream`` holds the
bounded-delay state of a session (``max_delay``).
"""
