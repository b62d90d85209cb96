"""A campaign's figures as the campaign plans them: their names, formats and when each can be drawn.

The campaign's process plans the figure jobs from these names alone and hands them to its worker
processes, which draw them (``campaign.draw_figure``, by ``figures.campaign_figure``): so the campaign's
process never imports matplotlib (0.6 s of a command's start on an H200's host, before its first render).
"""

from __future__ import annotations

__all__ = ["CAMPAIGN_FIGURES", "FIRST_PAIR_FIGURES", "FORMATS"]

#: A campaign's figures, by file stem (``figures.CAMPAIGN_FIGURES`` maps each to the function that draws it).
CAMPAIGN_FIGURES = ("fig4", "fig5", "fig_density", "fig_budget")
#: The campaign figures that read only the first pair file of each snapshot (a campaign draws them early).
FIRST_PAIR_FIGURES = frozenset({"fig4"})
#: Every figure's files: a 300 dpi PNG to look at, a vector PDF to print, a vector SVG to edit.
FORMATS = ("png", "pdf", "svg")
