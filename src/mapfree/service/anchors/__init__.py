"""Relocalization anchors: photos checked and stored once, methods pooled, anchors prepared and cached, queries
localized."""
