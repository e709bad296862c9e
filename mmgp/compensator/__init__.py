"""compensator"""
