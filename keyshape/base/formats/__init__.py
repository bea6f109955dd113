"""One module per file format keyshape reads or writes; algorithm modules never open files."""
