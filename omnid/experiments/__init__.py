"""Reproductions of the thesis' experiments (chapter 7) as functions returning tables."""
