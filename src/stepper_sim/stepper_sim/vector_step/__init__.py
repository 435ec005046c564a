"""The simulated AEC Vector Step: its device (`device`, with `modes`, `homing`, `interpolation`
and `storage`), NMT, SDO and PDO parts and its CAN network (`sim`).
"""
