"""Registration: from an observed cloud to the best library model and its pose."""
