"""What the user opens: glTF/USD/CSV export, the preview video and its renderer."""
