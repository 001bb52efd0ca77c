"""What a person looks at: figures, animation, markers and the display topics' bytes, run outputs."""
