def main():
    import zenrl.common
    print("ok", zenrl.common.__file__)
