"""Dense-mesh tools: Gaussian-RBF face-space deformation, key-point insertion,
facial transfer (002_dce09d5f5656b088.txt) and mesh registration (001_7296bf6ea73cabea.txt section 6)."""
