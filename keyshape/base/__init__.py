"""The ground floor of keyshape: shared by every stage, importing none of them."""
