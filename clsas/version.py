"""The package's version, in a module of its own so that the data types can name it in the files
they write without importing the whole package."""

__version__ = "0.1.0"
