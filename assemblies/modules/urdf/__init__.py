"""Module URDFs (package data; an __init__ so setuptools ships this directory)."""
