"""The simulated AEC Vector Step: its device, NMT, SDO and PDO parts and its CAN network (`sim`).
"""
