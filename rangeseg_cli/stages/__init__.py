"""The paper's stages (Al-Hujazi & Sood 1990, Sec. V and VII).

Heights, edges, linking, region growing, surfaces, the noise estimate and
the holdsite.
"""
