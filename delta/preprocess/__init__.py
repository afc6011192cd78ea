"""Frame preprocessing: person mattes, clothing and face parsing."""
