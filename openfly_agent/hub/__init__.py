"""Level-3 Hugging Face Hub release: model card, dataset card, push."""
