"""Level-1 data: episode schema, OpenFly readers, parquet writer, torch dataset and collator."""
